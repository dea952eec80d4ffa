"""Distributions of initial states around a scene (:mod:`hybridoc.problems.scene`'s
``[distribution]`` table): :class:`Spread`, :class:`DiscSpread`, :class:`Distribution`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.problems.fields import toml_str as _toml_str
from hybridoc.problems.fields import vec2 as _vec2

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems.scene import Scene

__all__ = ["DiscSpread", "Distribution", "Spread"]

_SPREAD_KINDS = ("uniform", "normal", "range")
_SPREAD_FIELDS = ("position", "velocity", "target")
_DIST_KEYS = {"seed", "max_tries", "discs"}


@dataclass(frozen=True)
class Spread:
    """How one 2-vector (a position, a velocity or a target) of a disc is drawn.

    Parameters
    ----------
    kind
        ``"uniform"``: the nominal value plus a uniform offset in ``[-w, w]`` per coordinate
        (``value`` = the half-widths ``(wx, wy)``); ``"normal"``: the nominal value plus a
        normal offset of standard deviation ``value = (sx, sy)``; ``"range"``: uniform in
        the absolute intervals ``value = ((x_low, x_high), (y_low, y_high))``.
    value
        See ``kind``. Widths and deviations are >= 0; a range has ``low <= high``.
    """

    kind: str
    value: Any

    def __post_init__(self) -> None:
        if self.kind not in _SPREAD_KINDS:
            raise SceneError(
                f"spread kind must be one of {', '.join(_SPREAD_KINDS)}, got {self.kind!r}"
            )
        what = f"{self.kind} spread"
        if self.kind == "range":
            v = self.value
            if isinstance(v, str) or not isinstance(v, Sequence | np.ndarray) or len(v) != 2:
                raise SceneError(f"{what} must be [[x_low, x_high], [y_low, y_high]], got {v!r}")
            pairs = (_vec2(v[0], f"{what} of x"), _vec2(v[1], f"{what} of y"))
            for axis, (lo, hi) in zip("xy", pairs, strict=True):
                if lo > hi:
                    raise SceneError(f"{what} of {axis}: low {lo} > high {hi}")
            object.__setattr__(self, "value", pairs)
        else:
            w = _vec2(self.value, what)
            if min(w) < 0:
                raise SceneError(f"{what} must be >= 0 in each coordinate, got {list(w)}")
            object.__setattr__(self, "value", w)

    def draw(self, rng: np.random.Generator, nominal: Sequence[float]) -> tuple[float, float]:
        """One draw around ``nominal`` (``range`` ignores it)."""
        if self.kind == "range":
            (xl, xh), (yl, yh) = self.value
            x = rng.uniform(0.0, 1.0, 2)
            return (float(xl + (xh - xl) * x[0]), float(yl + (yh - yl) * x[1]))
        if self.kind == "uniform":
            off = rng.uniform(-1.0, 1.0, 2) * np.asarray(self.value)
        else:
            off = rng.standard_normal(2) * np.asarray(self.value)
        return (float(nominal[0] + off[0]), float(nominal[1] + off[1]))

    @classmethod
    def from_value(cls, value: Any, what: str) -> Spread:
        """From the TOML form ``{ uniform = [wx, wy] }`` (or ``normal``, ``range``)."""
        if isinstance(value, Spread):
            return value
        if not isinstance(value, Mapping) or len(value) != 1:
            raise SceneError(
                f"{what} must be a table with one of the keys {', '.join(_SPREAD_KINDS)} "
                f"(e.g. {{ uniform = [0.3, 0.3] }}), got {value!r}"
            )
        ((kind, v),) = value.items()
        if kind not in _SPREAD_KINDS:
            raise SceneError(
                f"{what}: unknown spread {kind!r} (allowed: {', '.join(_SPREAD_KINDS)})"
            )
        try:
            return cls(kind, v)
        except SceneError as exc:
            raise SceneError(f"{what}: {exc}") from None

    def toml(self) -> str:
        """The TOML inline table."""
        if self.kind == "range":
            inner = ", ".join(f"[{lo!r}, {hi!r}]" for lo, hi in self.value)
            return f"{{ range = [{inner}] }}"
        return f"{{ {self.kind} = [{self.value[0]!r}, {self.value[1]!r}] }}"


@dataclass(frozen=True)
class DiscSpread:
    """What varies of one disc: its initial position, velocity and target (each optional).

    Parameters
    ----------
    name
        The disc's name in the scene.
    position, velocity, target
        A :class:`Spread` (or its TOML form, a one-key mapping) or ``None`` (fixed).
    """

    name: str
    position: Spread | None = None
    velocity: Spread | None = None
    target: Spread | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise SceneError(
                f"distribution: disc name must be a non-empty string, got {self.name!r}"
            )
        for f in _SPREAD_FIELDS:
            v = getattr(self, f)
            if v is not None:
                what = f"distribution.discs.{self.name}.{f}"
                object.__setattr__(self, f, Spread.from_value(v, what))


@dataclass(frozen=True)
class Distribution:
    """A distribution of initial states (and targets) around a scene.

    Each draw starts from the scene's nominal values and redraws what the disc spreads
    name. Draw ``i`` comes from its own random stream ``default_rng([seed, i])``, so it
    does not depend on how many draws are made or in which order. A draw whose discs
    overlap each other or a wall is rejected and redrawn, up to ``max_tries`` times.

    Parameters
    ----------
    discs
        One :class:`DiscSpread` per disc that varies (at most one per disc).
    seed
        Integer >= 0.
    max_tries
        Draws of one sample before :class:`~hybridoc.errors.SceneError`, >= 1.
    """

    discs: tuple[DiscSpread, ...] = ()
    seed: int = 0
    max_tries: int = 1000

    def __post_init__(self) -> None:
        for key in ("seed", "max_tries"):
            v = getattr(self, key)
            low = 0 if key == "seed" else 1
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low:
                raise SceneError(f"distribution: {key} must be an integer >= {low}, got {v!r}")
            object.__setattr__(self, key, int(v))
        discs = tuple(self.discs)
        for d in discs:
            if not isinstance(d, DiscSpread):
                raise SceneError(f"distribution: discs must be DiscSpread objects, got {d!r}")
        names = [d.name for d in discs]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise SceneError(f"distribution: disc(s) listed twice: {', '.join(dupes)}")
        if not any(getattr(d, f) is not None for d in discs for f in _SPREAD_FIELDS):
            raise SceneError(
                "distribution: nothing varies; give some disc a position, velocity or target spread"
            )
        object.__setattr__(self, "discs", discs)

    def check(self, scene: Scene) -> None:
        """Raise :class:`~hybridoc.errors.SceneError` if it does not fit ``scene``."""
        by_name = {d.name: d for d in scene.discs}
        for ds in self.discs:
            if ds.name not in by_name:
                raise SceneError(
                    f"distribution.discs.{ds.name}: no disc of that name "
                    f"(discs: {', '.join(by_name)})"
                )
            if ds.target is not None and by_name[ds.name].target is None:
                raise SceneError(
                    f"distribution.discs.{ds.name}.target: the disc has no target to vary"
                )

    @classmethod
    def from_dict(cls, data: Any) -> Distribution:
        """From the TOML ``[distribution]`` table (module docstring)."""
        if not isinstance(data, Mapping):
            raise SceneError("'distribution' must be a table ([distribution])")
        unknown = set(data) - _DIST_KEYS
        if unknown:
            raise SceneError(
                f"distribution: unknown key(s) {', '.join(sorted(unknown))} "
                f"(allowed: {', '.join(sorted(_DIST_KEYS))})"
            )
        raw = data.get("discs", {})
        if not isinstance(raw, Mapping):
            raise SceneError(
                "distribution.discs must be a table of disc names ([distribution.discs.NAME])"
            )
        discs = []
        for name, spec in raw.items():
            if not isinstance(spec, Mapping):
                raise SceneError(f"distribution.discs.{name} must be a table")
            unknown = set(spec) - set(_SPREAD_FIELDS)
            if unknown:
                raise SceneError(
                    f"distribution.discs.{name}: unknown key(s) {', '.join(sorted(unknown))} "
                    f"(allowed: {', '.join(_SPREAD_FIELDS)})"
                )
            discs.append(DiscSpread(name, **dict(spec)))
        kwargs = {k: data[k] for k in ("seed", "max_tries") if k in data}
        return cls(discs=tuple(discs), **kwargs)

    def toml_lines(self) -> list[str]:
        """The ``[distribution]`` table as TOML lines."""
        lines = ["[distribution]", f"seed = {self.seed}", f"max_tries = {self.max_tries}"]
        for d in self.discs:
            lines += ["", f"[distribution.discs.{_toml_str(d.name)}]"]
            for f in _SPREAD_FIELDS:
                sp = getattr(d, f)
                if sp is not None:
                    lines.append(f"{f} = {sp.toml()}")
        return lines

    def draw(self, scene: Scene, index: int, seed: int | None = None) -> Scene:
        """Draw ``index`` as a concrete scene (without a distribution).

        Raises
        ------
        SceneError
            No draw without overlaps within ``max_tries``.
        """
        seed = self.seed if seed is None else seed
        rng = np.random.default_rng([int(seed), int(index)])
        spreads = {d.name: d for d in self.discs}
        last = ""
        for _ in range(self.max_tries):
            discs = []
            for d in scene.discs:
                ds = spreads.get(d.name)
                if ds is None:
                    discs.append(d)
                    continue
                changes: dict[str, Any] = {}
                for f in _SPREAD_FIELDS:
                    sp = getattr(ds, f)
                    if sp is not None:
                        changes[f] = sp.draw(rng, getattr(d, f))
                discs.append(dataclasses.replace(d, **changes))
            try:
                return dataclasses.replace(scene, discs=tuple(discs), distribution=None)
            except SceneError as exc:
                last = str(exc)
        raise SceneError(
            f"distribution: sample {index} (seed {seed}): no draw without overlaps in "
            f"{self.max_tries} tries (last: {last}); narrow the spreads or raise max_tries"
        )
