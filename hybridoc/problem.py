"""One way to name a problem everywhere: :func:`as_ocp`.

Every entry point of hybridoc (the judge, the reference, the solvers, the CLI) accepts a
problem as

* a :class:`~hybridoc.HybridOCP`;
* a :class:`~hybridoc.problems.Scene` (disc scenes compile to a HybridOCP);
* a string or path: a built-in name (``hybridoc problems`` lists them), a ``.toml`` scene
  file, or ``path/to/file.py:function`` naming a function that takes no arguments and
  returns a HybridOCP or a Scene (``path/to/file.py`` alone when the file defines exactly
  one function called ``problem``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP

if TYPE_CHECKING:
    import numpy.typing as npt

    from hybridoc.problems.scene import Scene
    from hybridoc.solution import Solution

__all__ = ["ControlsLike", "ProblemLike", "as_ocp", "disc_scene"]

ProblemLike: TypeAlias = "HybridOCP | Scene | str | Path"
"""A HybridOCP, a Scene, a built-in name, a ``.toml`` path or ``file.py:function``."""

ControlsLike: TypeAlias = "npt.ArrayLike | Solution"
"""Piecewise-constant controls: an ``(N, nu)`` array (numpy, nested lists, a torch tensor)
or a :class:`~hybridoc.solution.Solution` whose controls are taken."""


def as_ocp(problem: ProblemLike) -> HybridOCP:
    """The :class:`~hybridoc.HybridOCP` of anything that names a problem (module notes).

    Raises
    ------
    hybridoc.errors.SceneError
        For an unknown name, an unreadable or invalid file, or an object that is not a
        problem.
    """
    if isinstance(problem, HybridOCP):
        return problem
    if isinstance(problem, str | Path):
        from hybridoc.problems import load_problem

        problem = load_problem(problem)
        if isinstance(problem, HybridOCP):
            return problem
    to_ocp = getattr(problem, "to_ocp", None)
    if to_ocp is None:
        raise SceneError(
            f"expected a problem (a HybridOCP, a Scene, a built-in name, a .toml file or "
            f"file.py:function), got {type(problem).__name__}"
        )
    ocp = to_ocp()
    if not isinstance(ocp, HybridOCP):
        raise SceneError(f"{type(problem).__name__}.to_ocp() did not return a HybridOCP")
    return ocp


def disc_scene(problem: ProblemLike) -> Scene:
    """The :class:`~hybridoc.problems.Scene` of a disc problem (a name, a Scene or a
    :class:`~hybridoc.problems.DiscOCP`), with the problem's current data.

    Raises
    ------
    hybridoc.errors.SceneError
        For a problem that is not a disc scene.
    """
    from hybridoc.problems import scene_of

    scene = scene_of(problem, compiled=False)
    if scene is not None:
        return scene
    ocp = as_ocp(problem)
    scene = scene_of(ocp)
    if scene is None:
        raise SceneError(
            f"{ocp.name!r} is not a disc scene (a generic HybridOCP): this needs a disc scene"
        )
    return scene
