"""Scenes: built-in problems and the TOML scene format (installed as ``hybridoc.problems``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from hybridoc.errors import SceneError
from hybridoc.problems.scene import Disc, Scene, Wall

__all__ = ["Disc", "Wall", "Scene", "builtin_names", "load_scene"]


def _builtin_dir() -> Path:
    return Path(str(resources.files("hybridoc.problems") / "scenes"))


def builtin_names() -> list[str]:
    """Names of the built-in scenes, sorted."""
    return sorted(p.stem for p in _builtin_dir().glob("*.toml"))


def load_scene(scene: str | Path | Scene) -> Scene:
    """Load a scene from a built-in name, a TOML path, or pass a :class:`Scene` through.

    Parameters
    ----------
    scene
        A built-in name (see :func:`builtin_names`), a path to a ``.toml`` file, or a Scene.

    Raises
    ------
    hybridoc.errors.SceneError
        If the name is unknown, the file cannot be read, or the scene is invalid.
    """
    if isinstance(scene, Scene):
        return scene
    text = str(scene)
    if text in builtin_names():
        return Scene.from_toml(_builtin_dir() / f"{text}.toml")
    path = Path(text)
    if path.suffix == ".toml" or path.exists():
        if not path.exists():
            raise SceneError(f"scene file {text!r} does not exist")
        return Scene.from_toml(path)
    raise SceneError(
        f"unknown scene {text!r}: not a built-in ({', '.join(builtin_names())}) "
        "and not a path to a .toml file"
    )
