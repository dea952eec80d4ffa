"""Declarative disc-and-wall scenes.

A scene is a TOML file or a :class:`Scene` object. Every field has a documented default or is
required; every invalid input raises :class:`~hybridoc.errors.SceneError` with one message
naming the problem.

TOML layout::

    name = "single-collision"          # optional, default: file stem
    description = "..."                # optional
    horizon = 1.0                      # T, required, > 0
    steps = 480                        # N, default 480, at most 10**6 (MAX_STEPS)
    control_weight = 0.01              # eps in eps*|u|^2, default 0.01, > 0
    restitution = 1.0                  # e in [0, 1], default 1.0

    [[discs]]
    name = "striker"                   # required, unique; [A-Za-z_][A-Za-z0-9_-]*
    position = [-1.0, -2.0]            # required
    velocity = [0.0, 0.0]              # default zeros
    radius = 0.2                       # required, > 0
    mass = 1.0                         # default 1, > 0
    actuated = true                    # default false
    initial_control = [0.0, 3.0]       # actuated discs only; a constant [ux, uy] or N rows
    target = [0.0, 0.0]                # optional: adds |p(T) - target|^2 to the terminal cost

    [[walls]]
    name = "ceiling"                   # optional, default "wall<k>"; as a disc name
    point = [0.0, 1.0]                 # required
    normal = [0.0, -1.0]               # required, nonzero, points into free space

    [distribution]                     # optional: initial states to draw (datasets)
    seed = 0                           # default 0
    max_tries = 1000                   # redraws of one sample before giving up
    [distribution.discs.ball2]         # one table per disc that varies
    position = { uniform = [0.3, 0.3] }   # nominal +- half-widths per coordinate
    velocity = { normal = [0.1, 0.1] }    # nominal + N(0, sigma^2) per coordinate
    target = { range = [[-0.1, 0.1], [0.0, 0.2]] }  # absolute [low, high] per coordinate

    [hints.gd]                         # optional: option defaults per method (solver hints)
    lr = 200.0                         # numbers, strings or booleans; a user's option wins
    iters = 500
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import checked_steps
from hybridoc.problems.distribution import DiscSpread, Distribution, Spread
from hybridoc.problems.fields import number as _number
from hybridoc.problems.fields import toml_str as _toml_str
from hybridoc.problems.fields import vec2 as _vec2

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems.disc_ocp import DiscOCP

__all__ = [
    "MAGNITUDE_RANGE",
    "MAX_OFFSET_RATIO",
    "MIN_RADIUS_RATIO",
    "NAME_PATTERN",
    "Disc",
    "DiscSpread",
    "Distribution",
    "Scene",
    "Spread",
    "Wall",
]

MAGNITUDE_RANGE = (1e-60, 1e60)
"""The supported magnitudes (issue #32): every number of a scene (coordinates, velocities,
forces, radii, masses, horizon) is at most ``1e60`` in magnitude, every positive one
(radius, mass, horizon) at least ``1e-60``, and so are the
scene's units (:func:`hybridoc.scales.disc_scales`: length, time, mass, and the velocity
and force units they make). The judge squares lengths, velocities and forces and the
rounding bounds square ``eps`` times them; inside this range none of these over- or
underflows (``1e120`` and ``1e-152`` at worst). The control weight (units of time^3 /
mass^2) is only required positive and finite, and so are the points of *far* bodies
(:data:`hybridoc.scales.FAR_FACTOR`: a disc parked at ``-2e300`` touches nothing, and its
gaps, which overflow to infinity, say so). Outside it a
:class:`~hybridoc.errors.SceneError` names the field (CLI exit 2): radii of ``1e-300``
square to zero, and the judge missed the contact (cost 2.09 against the closed form 1.393)."""

MIN_RADIUS_RATIO = 1e-9
"""Every radius (of a scene with contacts) is at least this fraction of the scene's
length scale (:attr:`Scales.length <hybridoc.scales.Scales.length>`). Positions round at
about ``2e-16`` lengths; at this ratio the contact geometry (where discs touch, the
collision normal) keeps about seven significant digits, and the judge's invariance under
units and moves is tested down to ``1e-6``."""

MAX_OFFSET_RATIO = 1e12
"""The scene's centre (:attr:`Scales.state_offset <hybridoc.scales.Scales.state_offset>`)
is at most this many length scales from the origin: the coordinates then still resolve
``1e-4`` lengths. The judge computes in the scene's local frame (exact), so within this
range a move changes nothing beyond the rounding of the coordinates themselves."""

NAME_PATTERN = r"[A-Za-z_][A-Za-z0-9_-]*"
"""What a disc or wall name may be: ASCII letters, digits, ``_`` and ``-``, not starting with
a digit or ``-``. Names become guard names (``a|b``), control labels (``a.ux``), entries of
``--sequence`` lists (comma-separated) and parts of compiled CasADi function names, which
take ASCII only."""
_NAME_RE = re.compile(NAME_PATTERN)

_TOP_KEYS = {"name", "description", "horizon", "steps", "control_weight", "restitution"}
_DISC_KEYS = {
    "name",
    "position",
    "velocity",
    "radius",
    "mass",
    "actuated",
    "initial_control",
    "target",
}
_WALL_KEYS = {"name", "point", "normal"}
_TABLES = {"discs", "walls", "distribution", "hints"}


def _check_name(name: str, what: str) -> None:
    if _NAME_RE.fullmatch(name) is None:
        raise SceneError(
            f"{what} name {name!r} is not allowed: use ASCII letters, digits, '_' and '-', "
            "starting with a letter or '_' (names make up guard names such as 'a|b', control "
            "labels such as 'a.ux' and compiled function names)"
        )


def _positive(value: Any, what: str) -> float:
    x = _number(value, what)
    if x <= 0:
        raise SceneError(f"{what} must be positive, got {x}")
    return x


@dataclass(frozen=True)
class Disc:
    """A rigid disc in the plane.

    Parameters
    ----------
    name
        Unique name, used in event reports; matches :data:`NAME_PATTERN`.
    position
        Initial centre ``[x, y]``.
    radius
        Radius, > 0.
    velocity
        Initial velocity ``[vx, vy]``; default zeros.
    mass
        Mass, > 0; default 1.
    actuated
        Whether a force ``[ux, uy]`` acts on this disc (a control input).
    initial_control
        Initial guess of the force for solvers: ``None`` (zeros), a constant ``[ux, uy]``,
        or an ``(N, 2)`` array. Only for actuated discs.
    target
        Optional target position; adds ``|p(T) - target|^2`` to the terminal cost.
    """

    name: str
    position: tuple[float, float]
    radius: float
    velocity: tuple[float, float] = (0.0, 0.0)
    mass: float = 1.0
    actuated: bool = False
    initial_control: Any = None
    target: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        what = f"disc {self.name!r}"
        if not isinstance(self.name, str) or not self.name.strip():
            raise SceneError(f"disc name must be a non-empty string, got {self.name!r}")
        _check_name(self.name, "disc")
        object.__setattr__(self, "position", _vec2(self.position, f"{what}: position"))
        object.__setattr__(self, "velocity", _vec2(self.velocity, f"{what}: velocity"))
        object.__setattr__(self, "radius", _positive(self.radius, f"{what}: radius"))
        object.__setattr__(self, "mass", _positive(self.mass, f"{what}: mass"))
        if not isinstance(self.actuated, bool | np.bool_):
            raise SceneError(f"{what}: actuated must be true or false, got {self.actuated!r}")
        object.__setattr__(self, "actuated", bool(self.actuated))
        if self.target is not None:
            object.__setattr__(self, "target", _vec2(self.target, f"{what}: target"))
        if self.initial_control is not None:
            if not self.actuated:
                raise SceneError(f"{what}: initial_control given but the disc is not actuated")
            arr = np.asarray(self.initial_control, dtype=object)
            if arr.ndim == 1:
                u = np.array(_vec2(self.initial_control, f"{what}: initial_control"))
            elif arr.ndim == 2 and arr.shape[1] == 2:
                u = np.array(
                    [_vec2(row, f"{what}: initial_control row") for row in self.initial_control]
                )
            else:
                raise SceneError(
                    f"{what}: initial_control must be [ux, uy] or a list of N [ux, uy] rows"
                )
            u.setflags(write=False)
            object.__setattr__(self, "initial_control", u)

    def _key(self) -> tuple[Any, ...]:
        u = self.initial_control
        u_key = None if u is None else (u.shape, tuple(u.ravel().tolist()))
        fields = (self.name, self.position, self.radius, self.velocity, self.mass)
        return (*fields, self.actuated, u_key, self.target)

    # initial_control is an array: compare and hash it by value (the generated dataclass
    # methods would fail on it)
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Disc):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())


@dataclass(frozen=True)
class Wall:
    """An infinite straight wall through ``point`` with ``normal`` pointing into free space.

    The normal is normalised to unit length; a zero-length normal is an error. A name, when
    given, matches :data:`NAME_PATTERN`; an empty one becomes ``wall<k>`` in the scene.
    """

    point: tuple[float, float]
    normal: tuple[float, float]
    name: str = ""

    def __post_init__(self) -> None:
        what = f"wall {self.name!r}" if self.name else "wall"
        object.__setattr__(self, "point", _vec2(self.point, f"{what}: point"))
        n = _vec2(self.normal, f"{what}: normal")
        length = math.hypot(*n)
        if length < 1e-12:
            raise SceneError(f"{what}: normal has zero length")
        # a normal that is already unit up to rounding is kept as given, so that normalising
        # is idempotent and to_toml -> from_toml reproduces the wall bit for bit
        if abs(length - 1.0) > 4 * np.finfo(float).eps:
            n = (n[0] / length, n[1] / length)
        object.__setattr__(self, "normal", n)
        if not isinstance(self.name, str):
            raise SceneError(f"wall name must be a string, got {self.name!r}")
        if self.name:  # empty: the scene names it wall<k>
            _check_name(self.name, "wall")


def _first_overlap(discs: Sequence[Disc], block: int = 256) -> tuple[int, int, float] | None:
    """The first pair ``(i, j, gap)``, ``i < j`` in scene order, of discs that overlap at
    ``t = 0`` beyond the rounding of their coordinates (``1e-12`` times the largest
    magnitude among their coordinates and radii), else ``None``. Vectorised by blocks of
    rows: a scene of 2000 discs (2 million pairs) is checked in well under a second, where
    a Python loop over the pairs took 9 s."""
    n = len(discs)
    if n < 2:
        return None
    p = np.array([d.position for d in discs], dtype=float)
    r = np.array([d.radius for d in discs], dtype=float)
    size = np.abs(p).max(axis=1)
    for i0 in range(0, n - 1, block):
        i1 = min(i0 + block, n - 1)
        rows = np.arange(i0, i1)[:, None]
        cols = np.arange(n)[None, :]
        later = cols > rows
        d = p[i0:i1, None, :] - p[None, :, :]
        rr = r[i0:i1, None] + r[None, :]
        gap = np.hypot(d[..., 0], d[..., 1]) - rr
        slack = 1e-12 * np.maximum(np.maximum(size[i0:i1, None], size[None, :]), rr)
        bad = later & (gap < -slack)
        if bad.any():
            k = int(np.argmax(bad.ravel()))  # row-major: the first i, then the first j
            i, j = divmod(k, n)
            return i0 + i, j, float(gap[i, j])
    return None


@dataclass(frozen=True)
class Scene:
    """A disc-and-wall optimal control problem.

    Cost: ``sum over discs with a target of |p_i(T) - target_i|^2 + integral eps |u|^2 dt``
    with ``u`` the stacked forces of the actuated discs (scene order).

    Parameters
    ----------
    horizon
        Final time ``T`` > 0.
    discs
        The discs; at least one actuated, at least one with a target.
    walls
        The walls (may be empty).
    steps
        ``N``: grid of the discrete solvers and of sampled controls; at most
        :data:`~hybridoc.ocp.MAX_STEPS`.
    control_weight
        ``eps`` > 0.
    restitution
        Coefficient of restitution ``e`` in [0, 1] for all contacts.
    name, description
        Free text.
    distribution
        Optional :class:`Distribution` of initial states (and targets) around this scene,
        for :meth:`draw_scenes` and datasets.
    hints
        Solver hints: per method name (``"gd"``), option defaults the scene's author tuned
        (``{"lr": 200.0, "iters": 500}``); names match :data:`NAME_PATTERN`, values are
        finite numbers, strings or booleans. They reach the methods as
        :meth:`Capabilities.hints_for <hybridoc.capabilities.Capabilities.hints_for>`, and a
        user's option wins. Read-only.
    """

    horizon: float
    discs: tuple[Disc, ...]
    walls: tuple[Wall, ...] = ()
    steps: int = 480
    control_weight: float = 0.01
    restitution: float = 1.0
    name: str = "scene"
    description: str = ""
    distribution: Distribution | None = None
    hints: Mapping[str, Mapping[str, Any]] = field(default_factory=dict, hash=False)
    _derived: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "horizon", _positive(self.horizon, "horizon"))
        object.__setattr__(self, "steps", checked_steps(self.steps))
        object.__setattr__(self, "control_weight", _positive(self.control_weight, "control_weight"))
        e = _number(self.restitution, "restitution")
        if not 0.0 <= e <= 1.0:
            raise SceneError(f"restitution must lie in [0, 1], got {e}")
        object.__setattr__(self, "restitution", e)
        discs = tuple(self.discs)
        walls = tuple(self.walls)
        for d in discs:
            if not isinstance(d, Disc):
                raise SceneError(f"discs must be Disc objects, got {d!r}")
        for w in walls:
            if not isinstance(w, Wall):
                raise SceneError(f"walls must be Wall objects, got {w!r}")
        if not discs:
            raise SceneError("scene has no discs")
        names = [d.name for d in discs]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise SceneError(f"disc names must be unique; repeated: {', '.join(dupes)}")
        walls = tuple(
            w if w.name else Wall(point=w.point, normal=w.normal, name=f"wall{k}")
            for k, w in enumerate(walls)
        )
        wnames = [w.name for w in walls]
        wd = sorted({n for n in wnames if wnames.count(n) > 1} | (set(wnames) & set(names)))
        if wd:
            raise SceneError(f"wall names must be unique and differ from disc names: {wd}")
        object.__setattr__(self, "discs", discs)
        object.__setattr__(self, "walls", walls)
        if not any(d.actuated for d in discs):
            raise SceneError("scene has no actuated disc: nothing to control")
        if not any(d.target is not None for d in discs):
            raise SceneError("scene has nothing in the terminal cost: give some disc a target")
        for d in discs:
            u = d.initial_control
            if u is not None and u.ndim == 2 and u.shape[0] != self.steps:
                raise SceneError(
                    f"disc {d.name!r}: initial_control has {u.shape[0]} rows, expected "
                    f"steps = {self.steps}"
                )

        # touching is allowed; so is an overlap at the rounding level of the coordinates
        # (e.g. a disc of radius 0.2 at y = -0.8 on the wall y = -1 computes a gap of -6e-17)
        # (relative to the magnitudes alone, radii among them: a scene in micrometres gets
        # a slack in micrometres)
        def slack(*xs: float) -> float:
            return 1e-12 * max(abs(x) for x in xs)

        overlap = _first_overlap(discs)
        if overlap is not None:
            i, j, gap = overlap
            raise SceneError(
                f"discs {discs[i].name!r} and {discs[j].name!r} overlap at t = 0 "
                f"(penetration {-gap:.6g})"
            )
        for a in discs:
            for w in walls:
                gap = (a.position[0] - w.point[0]) * w.normal[0] + (
                    a.position[1] - w.point[1]
                ) * w.normal[1]
                gap -= a.radius
                if gap < -slack(*a.position, *w.point, a.radius):
                    raise SceneError(
                        f"disc {a.name!r} overlaps wall {w.name!r} at t = 0 "
                        f"(penetration {-gap:.6g}; the wall normal points into free space)"
                    )
        object.__setattr__(self, "hints", _checked_hints(self.hints))
        self._check_range()
        if self.distribution is not None:
            if not isinstance(self.distribution, Distribution):
                raise SceneError(
                    f"distribution must be a Distribution, got {type(self.distribution).__name__}"
                )
            self.distribution.check(self)

    def _check_range(self) -> None:
        """The supported range (:data:`MAGNITUDE_RANGE`, :data:`MIN_RADIUS_RATIO`,
        :data:`MAX_OFFSET_RATIO`): one :class:`SceneError` naming the first field outside."""
        from hybridoc.scales import disc_scales, far_points

        lo, hi = MAGNITUDE_RANGE
        rng = f"the supported range is [{lo:g}, {hi:g}] (hybridoc.problems.scene.MAGNITUDE_RANGE)"
        # not the control weight: a coefficient of units time^3 / mass^2, never squared
        # nor the points of far bodies (hybridoc.scales.FAR_FACTOR): a disc parked at 1e300
        # touches nothing, and its gaps, which overflow to inf, say so
        numbers: list[tuple[str, Any, bool]] = [("horizon", self.horizon, True)]
        points: list[tuple[str, Any]] = []
        for d in self.discs:
            w = f"disc {d.name!r}"
            numbers += [(f"{w}: radius", d.radius, True), (f"{w}: mass", d.mass, True)]
            numbers += [(f"{w}: velocity", d.velocity, False)]
            points.append((f"{w}: position", d.position))
            if d.initial_control is not None:
                numbers.append((f"{w}: initial_control", d.initial_control, False))
        points += [(f"disc {d.name!r}: target", d.target) for d in self.discs if d.target]
        points += [(f"wall {wall.name!r}: point", wall.point) for wall in self.walls]
        far = far_points(np.array([p for _, p in points]), [d.radius for d in self.discs])
        numbers += [(what, p, False) for (what, p), f in zip(points, far, strict=True) if not f]
        for what, value, positive in numbers:
            mag = np.abs(np.asarray(value, dtype=float))
            if mag.size and float(mag.max()) > hi:
                raise SceneError(f"{what}: {float(mag.max()):.3g} is too large; {rng}")
            if positive and float(mag.min()) < lo:
                raise SceneError(f"{what}: {float(mag.min()):.3g} is too small; {rng}")
        sc = disc_scales(
            [d.position for d in self.discs],
            [d.radius for d in self.discs],
            [d.mass for d in self.discs],
            [d.target for d in self.discs if d.target is not None],
            self.horizon,
            [d.mass for d in self.discs if d.actuated],
            [w.point for w in self.walls],
        )
        L, T = sc.length, sc.time
        M = sc.control[0] * T**2 / L if sc.control else 1.0
        units = {"length": L, "time": T, "mass": M, "velocity": L / T, "force": M * L / T**2}
        for name, v in units.items():
            if not lo <= v <= hi:
                raise SceneError(
                    f"the scene's {name} unit {v:.3g} (from its positions, radii, horizon and "
                    f"masses) lies outside the supported range [{lo:g}, {hi:g}] "
                    "(hybridoc.problems.scene.MAGNITUDE_RANGE)"
                )
        # (a lone disc without walls has no contact to lose)
        for d in self.discs if len(self.discs) > 1 or self.walls else ():
            if d.radius < MIN_RADIUS_RATIO * L:
                raise SceneError(
                    f"disc {d.name!r}: radius {d.radius:.3g} is below the supported "
                    f"{MIN_RADIUS_RATIO:g} x the scene's length scale {L:.3g} "
                    "(hybridoc.problems.scene.MIN_RADIUS_RATIO): its contacts would be lost "
                    "in the rounding of the positions"
                )
        off = float(np.max(np.abs(sc.offset_array), initial=0.0))
        if off > MAX_OFFSET_RATIO * L:
            raise SceneError(
                f"the discs lie {off:.3g} from the origin, more than the supported "
                f"{MAX_OFFSET_RATIO:g} x their length scale {L:.3g} "
                "(hybridoc.problems.scene.MAX_OFFSET_RATIO): move the scene nearer the origin"
            )

    # ------------------------------------------------------------------ layout helpers
    @property
    def n_discs(self) -> int:
        """Number of discs."""
        return len(self.discs)

    @property
    def actuated_indices(self) -> list[int]:
        """Indices (scene order) of the actuated discs."""
        return [i for i, d in enumerate(self.discs) if d.actuated]

    @property
    def n_controls(self) -> int:
        """Control dimension: 2 per actuated disc."""
        return 2 * len(self.actuated_indices)

    @property
    def dt(self) -> float:
        """Grid step ``T / N``."""
        return self.horizon / self.steps

    def initial_state(self) -> np.ndarray:
        """State ``s = [p_1, ..., p_n, v_1, ..., v_n]`` (x, y per disc) at t = 0."""
        p = np.array([d.position for d in self.discs], dtype=float).ravel()
        v = np.array([d.velocity for d in self.discs], dtype=float).ravel()
        return np.concatenate([p, v])

    def initial_controls(self) -> np.ndarray:
        """The initial guess as an ``(N, n_controls)`` array."""
        cols = []
        for i in self.actuated_indices:
            u = self.discs[i].initial_control
            if u is None:
                cols.append(np.zeros((self.steps, 2)))
            elif u.ndim == 1:
                cols.append(np.tile(u, (self.steps, 1)))
            else:
                cols.append(np.array(u, dtype=float))
        return np.hstack(cols)

    def control_labels(self) -> list[str]:
        """Column labels of the control array, e.g. ``['striker.ux', 'striker.uy']``."""
        return [f"{self.discs[i].name}.{c}" for i in self.actuated_indices for c in ("ux", "uy")]

    def time_grid(self) -> np.ndarray:
        """The ``N + 1`` grid times ``0, dt, ..., T``."""
        return np.linspace(0.0, self.horizon, self.steps + 1)

    def with_initial_state(self, state: Any) -> Scene:
        """The same scene with the discs starting from ``state`` (the hybridoc layout
        ``[p_1, ..., p_n, v_1, ..., v_n]``); validated like any scene (overlaps)."""
        x = np.asarray(state, dtype=float).ravel()
        n = self.n_discs
        if x.shape != (4 * n,):
            raise SceneError(f"state must have {4 * n} entries, got shape {x.shape}")
        discs = tuple(
            dataclasses.replace(
                d,
                position=(float(x[2 * i]), float(x[2 * i + 1])),
                velocity=(float(x[2 * n + 2 * i]), float(x[2 * n + 2 * i + 1])),
            )
            for i, d in enumerate(self.discs)
        )
        return dataclasses.replace(self, discs=discs)

    def with_steps(self, steps: int) -> Scene:
        """The same scene on another grid (constant initial controls are kept)."""
        discs = []
        for d in self.discs:
            u = d.initial_control
            if u is not None and u.ndim == 2:
                # sample the old piecewise-constant guess at the new cell midpoints
                t_new = (np.arange(steps) + 0.5) / steps
                u = u[np.minimum((t_new * self.steps).astype(int), self.steps - 1)]
            discs.append(
                Disc(
                    name=d.name,
                    position=d.position,
                    radius=d.radius,
                    velocity=d.velocity,
                    mass=d.mass,
                    actuated=d.actuated,
                    initial_control=u,
                    target=d.target,
                )
            )
        return Scene(
            horizon=self.horizon,
            discs=tuple(discs),
            walls=self.walls,
            steps=steps,
            control_weight=self.control_weight,
            restitution=self.restitution,
            name=self.name,
            description=self.description,
            distribution=self.distribution,
            hints=self.hints,
        )

    def to_ocp(self) -> DiscOCP:
        """Compile to a :class:`~hybridoc.problems.DiscOCP` (cached)."""
        if "ocp" not in self._derived:
            from hybridoc.problems.compile import scene_to_ocp

            self._derived["ocp"] = scene_to_ocp(self)
        return self._derived["ocp"]

    # ------------------------------------------------------------------ distributions
    def _require_distribution(self) -> Distribution:
        if self.distribution is None:
            raise SceneError(f"scene {self.name!r} has no [distribution] table: nothing to draw")
        return self.distribution

    def draw_scenes(self, samples: int, seed: int | None = None, *, start: int = 0) -> list[Scene]:
        """Concrete scenes drawn from :attr:`distribution` (see :class:`Distribution`).

        Parameters
        ----------
        samples
            How many, >= 1.
        seed
            Overrides the distribution's seed.
        start
            Index of the first draw (draw ``i`` is the same whatever ``samples``).

        Returns
        -------
        list of Scene
            Scenes without a distribution, named ``<name>#<i>``.
        """
        dist = self._require_distribution()
        if isinstance(samples, bool) or not isinstance(samples, int | np.integer) or samples < 1:
            raise SceneError(f"samples must be an integer >= 1, got {samples!r}")
        if seed is not None and (
            isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0
        ):
            raise SceneError(f"seed must be an integer >= 0, got {seed!r}")
        out = []
        for i in range(int(start), int(start) + int(samples)):
            sc = dist.draw(self, i, seed)
            out.append(dataclasses.replace(sc, name=f"{self.name}#{i}"))
        return out

    def sample_initial_states(self, samples: int, seed: int | None = None) -> np.ndarray:
        """The initial states of :meth:`draw_scenes`, shape ``(samples, 4 n_discs)``."""
        return np.array([s.initial_state() for s in self.draw_scenes(samples, seed)])

    def targets(self) -> np.ndarray:
        """Targets per disc, shape ``(n_discs, 2)``; NaN for discs without one."""
        return np.array(
            [d.target if d.target is not None else (np.nan, np.nan) for d in self.discs]
        )

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, default_name: str = "scene") -> Scene:
        """Build a scene from a mapping with the TOML layout (see module docstring)."""
        if not isinstance(data, Mapping):
            raise SceneError(f"scene must be a table, got {type(data).__name__}")
        unknown = set(data) - _TOP_KEYS - _TABLES
        if unknown:
            raise SceneError(
                f"unknown top-level key(s): {', '.join(sorted(unknown))} "
                f"(allowed: {', '.join(sorted(_TOP_KEYS | _TABLES))})"
            )
        if "horizon" not in data:
            raise SceneError("missing required key 'horizon'")
        discs_raw = data.get("discs")
        if discs_raw is None:
            raise SceneError("missing required [[discs]] tables")
        if not isinstance(discs_raw, list):
            raise SceneError("'discs' must be an array of tables ([[discs]])")
        discs = []
        for k, d in enumerate(discs_raw):
            if not isinstance(d, Mapping):
                raise SceneError(f"discs[{k}] must be a table")
            label = f"discs[{k}]" + (f" ({d['name']!r})" if "name" in d else "")
            unknown = set(d) - _DISC_KEYS
            if unknown:
                raise SceneError(
                    f"{label}: unknown key(s) {', '.join(sorted(unknown))} "
                    f"(allowed: {', '.join(sorted(_DISC_KEYS))})"
                )
            for req in ("name", "position", "radius"):
                if req not in d:
                    raise SceneError(f"{label}: missing required key {req!r}")
            if not isinstance(d["name"], str):
                raise SceneError(f"{label}: name must be a string, got {d['name']!r}")
            discs.append(Disc(**dict(d)))
        walls_raw = data.get("walls", [])
        if not isinstance(walls_raw, list):
            raise SceneError("'walls' must be an array of tables ([[walls]])")
        walls = []
        for k, w in enumerate(walls_raw):
            if not isinstance(w, Mapping):
                raise SceneError(f"walls[{k}] must be a table")
            unknown = set(w) - _WALL_KEYS
            if unknown:
                raise SceneError(
                    f"walls[{k}]: unknown key(s) {', '.join(sorted(unknown))} "
                    f"(allowed: {', '.join(sorted(_WALL_KEYS))})"
                )
            for req in ("point", "normal"):
                if req not in w:
                    raise SceneError(f"walls[{k}]: missing required key {req!r}")
            walls.append(Wall(**dict(w)))
        name = data.get("name", default_name)
        description = data.get("description", "")
        if not isinstance(name, str) or not isinstance(description, str):
            raise SceneError("name and description must be strings")
        kwargs: dict[str, Any] = {}
        for key in ("steps", "control_weight", "restitution"):
            if key in data:
                kwargs[key] = data[key]
        if "distribution" in data:
            kwargs["distribution"] = Distribution.from_dict(data["distribution"])
        if "hints" in data:
            kwargs["hints"] = data["hints"]
        return cls(
            horizon=data["horizon"],
            discs=tuple(discs),
            walls=tuple(walls),
            name=name,
            description=description,
            **kwargs,
        )

    @classmethod
    def from_toml(cls, path: str | Path) -> Scene:
        """Read a scene from a TOML file."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise SceneError(f"cannot read scene file {str(path)!r}: {exc.strerror}") from None
        except UnicodeDecodeError:
            raise SceneError(f"scene file {str(path)!r} is not UTF-8 text") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(f"scene file {str(path)!r} is not valid TOML: {exc}") from None
        try:
            return cls.from_dict(data, default_name=path.stem)
        except SceneError as exc:
            raise SceneError(f"scene file {str(path)!r}: {exc}") from None

    def to_toml(self) -> str:
        """Serialise to TOML text that :meth:`from_toml` reads back to an equal scene."""

        def f(x: float) -> str:
            return repr(float(x))

        def v(p: Sequence[float]) -> str:
            return "[" + ", ".join(f(x) for x in p) + "]"

        lines = [
            f"name = {_toml_str(self.name)}",
            f"description = {_toml_str(self.description)}",
            f"horizon = {f(self.horizon)}",
            f"steps = {self.steps}",
            f"control_weight = {f(self.control_weight)}",
            f"restitution = {f(self.restitution)}",
        ]
        for d in self.discs:
            lines += [
                "",
                "[[discs]]",
                f"name = {_toml_str(d.name)}",
                f"position = {v(d.position)}",
                f"velocity = {v(d.velocity)}",
                f"radius = {f(d.radius)}",
                f"mass = {f(d.mass)}",
                f"actuated = {'true' if d.actuated else 'false'}",
            ]
            if d.initial_control is not None:
                u = d.initial_control
                txt = v(u) if u.ndim == 1 else "[" + ", ".join(v(r) for r in u) + "]"
                lines.append(f"initial_control = {txt}")
            if d.target is not None:
                lines.append(f"target = {v(d.target)}")
        for w in self.walls:
            lines += [
                "",
                "[[walls]]",
                f"name = {_toml_str(w.name)}",
                f"point = {v(w.point)}",
                f"normal = {v(w.normal)}",
            ]
        if self.distribution is not None:
            lines += ["", *self.distribution.toml_lines()]
        for method, options in self.hints.items():
            lines += ["", f"[hints.{method}]"]
            lines += [f"{key} = {_toml_value(value)}" for key, value in options.items()]
        return "\n".join(lines) + "\n"


def _hint_value(value: Any, what: str) -> float | int | str | bool:
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, str):
        return value
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        return _number(value, what)
    raise SceneError(f"{what} must be a number, a string or a boolean, got {value!r}")


def _checked_hints(hints: Any) -> dict[str, dict[str, Any]]:
    """A validated copy of a scene's ``hints`` (method -> option -> value), or one
    :class:`SceneError` line naming the first bad entry."""
    if not isinstance(hints, Mapping):
        raise SceneError(
            "hints must be a table of methods ([hints.gd] with option = value lines), "
            f"got {hints!r}"
        )
    out: dict[str, dict[str, Any]] = {}
    for method, options in hints.items():
        if not isinstance(method, str) or _NAME_RE.fullmatch(method) is None:
            raise SceneError(f"hints: method name {method!r} is not allowed ({NAME_PATTERN})")
        if not isinstance(options, Mapping):
            raise SceneError(f"hints.{method} must be a table of option = value, got {options!r}")
        table: dict[str, Any] = {}
        for key, value in options.items():
            if not isinstance(key, str) or _NAME_RE.fullmatch(key) is None:
                raise SceneError(
                    f"hints.{method}: option name {key!r} is not allowed ({NAME_PATTERN})"
                )
            table[key] = _hint_value(value, f"hints.{method}.{key}")
        out[method] = table
    return out


def _toml_value(value: float | int | str | bool) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return _toml_str(value)
    return repr(value)  # an int, or a finite float (repr reads back bit for bit)
