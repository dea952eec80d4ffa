"""The typed disc model: a :class:`~hybridoc.HybridOCP` that knows its
:class:`~hybridoc.problems.Scene`.

Code that treats disc scenes differently (the disc simulator, contact models, aimed starts,
geometric pruning of event sequences) asks ``isinstance(ocp, DiscOCP)`` and reads
``ocp.scene``; nothing looks up a ``meta`` key.
"""

from __future__ import annotations

import dataclasses
import threading
import weakref
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP, Structure

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems.scene import Scene

__all__ = ["DiscOCP", "translated"]

# the structures that scene_to_ocp compiled (a DiscOCP whose functions were replaced has
# another structure, which its scene no longer describes), each with its local frame's
# problem once built
_COMPILED: weakref.WeakKeyDictionary[Structure, list[HybridOCP | None]] = (
    weakref.WeakKeyDictionary()
)
_LOCK = threading.RLock()  # local_frame compiles, which marks the new structure


def translated(scene: Scene, shift: np.ndarray) -> Scene:
    """``scene`` moved by ``shift`` (positions, targets and wall points), without its
    distribution. Exact where ``shift`` is a snapped offset (:func:`hybridoc.scales.snap_offset`)
    taken off coordinates near it."""
    sh = np.asarray(shift, dtype=float)

    def mv(x: tuple[float, float]) -> tuple[float, float]:
        return (float(x[0] + sh[0]), float(x[1] + sh[1]))

    discs = tuple(
        dataclasses.replace(
            d, position=mv(d.position), target=None if d.target is None else mv(d.target)
        )
        for d in scene.discs
    )
    walls = tuple(dataclasses.replace(w, point=mv(w.point)) for w in scene.walls)
    return dataclasses.replace(scene, discs=discs, walls=walls, distribution=None)


@dataclass(eq=False)
class DiscOCP(HybridOCP):
    """The hybrid OCP of a disc scene (:meth:`Scene.to_ocp <hybridoc.problems.Scene.to_ocp>`).

    Parameters
    ----------
    source_scene
        The scene the problem was compiled from. The other parameters are those of
        :class:`~hybridoc.HybridOCP`.

    Notes
    -----
    :meth:`HybridOCP.replace` may change the problem's data (``steps``, ``horizon``,
    ``x0``); :attr:`scene` is the scene of the data as they are now.
    """

    source_scene: Scene | None = field(default=None, repr=False)

    DATA_FIELDS: ClassVar[frozenset[str]] = HybridOCP.DATA_FIELDS | {"source_scene"}

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.source_scene is None:
            raise SceneError("a DiscOCP needs the Scene it was compiled from (source_scene)")

    def mark_compiled(self) -> None:
        """Record that this problem's functions are those of :attr:`source_scene` (called by
        :func:`~hybridoc.problems.compile.scene_to_ocp`): only then may :meth:`local_frame`
        compile the scene again, moved."""
        with _LOCK:
            _COMPILED.setdefault(self.structure, [None])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_scene_cache", None)
        # whether the functions are the scene's travels with a pickle (a worker process)
        state["_scene_compiled"] = self.structure in _COMPILED
        return state

    def __setstate__(self, state: dict) -> None:
        compiled = state.pop("_scene_compiled", False)
        self.__dict__.update(state)
        if compiled:
            self.mark_compiled()

    def local_frame(self) -> tuple[HybridOCP, np.ndarray] | None:
        """The same problem with every position taken relative to the scales' offset, and
        that offset: ``(local, offset)`` with ``state = local_state + offset`` exactly.

        A scene far from the origin (positions near ``1e6``) keeps its numbers at the
        rounding of ``1e6`` in its own coordinates; in the local frame they round at the
        scene's own length scale, so the judge computes there (issue #32). ``None`` where the
        offset is zero, or where the problem's functions are not its scene's (a
        :meth:`~hybridoc.HybridOCP.replace` that changed them).
        """
        off = self.scales.offset_array
        slot = _COMPILED.get(self.structure)
        if slot is None or not off.any():
            return None
        with _LOCK:
            if slot[0] is None:
                scene = self.source_scene
                assert scene is not None
                n = scene.n_discs
                local = translated(scene, -off[:2]).to_ocp()
                if not np.array_equal(local.scales.offset_array, np.zeros(4 * n)):
                    return None  # pragma: no cover - the snapped centre moves by < 1 quantum
                slot[0] = local
            base = slot[0]
        assert base is not None
        local_ocp = base.replace(
            x0=self.x0 - off,
            horizon=self.horizon,
            steps=self.steps,
            u_guess=self.u_guess,
            u_min=self.u_min,
            u_max=self.u_max,
            name=self.name,
            horizon_bounds=self.horizon_bounds,
        )
        return local_ocp, off

    @property
    def scene(self) -> Scene:
        """The scene of this problem's data (steps, horizon and initial state as they are)."""
        scene = self.source_scene
        assert scene is not None
        key = (self.steps, self.horizon, self.x0.tobytes())
        cached = self.__dict__.get("_scene_cache")
        if cached is not None and cached[0] == key:
            return cached[1]
        if self.steps != scene.steps:
            scene = scene.with_steps(self.steps)
        if self.horizon != scene.horizon:
            scene = dataclasses.replace(scene, horizon=self.horizon)
        if not np.array_equal(self.x0, scene.initial_state()):
            scene = scene.with_initial_state(self.x0)
        self.__dict__["_scene_cache"] = (key, scene)
        return scene
