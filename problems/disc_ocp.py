"""The typed disc model: a :class:`~hybridoc.HybridOCP` that knows its
:class:`~hybridoc.problems.Scene`.

Code that treats disc scenes differently (the disc simulator, contact models, aimed starts,
geometric pruning of event sequences) asks ``isinstance(ocp, DiscOCP)`` and reads
``ocp.scene``; nothing looks up a ``meta`` key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems.scene import Scene

__all__ = ["DiscOCP"]


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
