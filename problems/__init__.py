"""Problems: disc scenes (the TOML format), the built-in scenes and the library of classic
hybrid OCPs (installed as ``hybridoc.problems``).

:func:`load_problem` resolves every way a problem can be named (see
:func:`hybridoc.problem.as_ocp`): a built-in scene, a library problem, a ``.toml`` file or
``path/to/file.py:function``.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc._pyfile import exit_message, import_file
from hybridoc.errors import SceneError
from hybridoc.problems.disc_ocp import DiscOCP
from hybridoc.problems.scene import Disc, Scene, Wall

if TYPE_CHECKING:
    from hybridoc.ocp import HybridOCP

__all__ = [
    "Disc",
    "DiscOCP",
    "Scene",
    "Wall",
    "builtin_names",
    "from_spec",
    "library_names",
    "library_ocp",
    "load_problem",
    "load_scene",
    "load_spec",
    "scene_of",
    "spec_of",
]


def _builtin_dir() -> Path:
    return Path(str(resources.files("hybridoc.problems") / "scenes"))


def builtin_names() -> list[str]:
    """Names of the built-in disc scenes, sorted."""
    return sorted(p.stem for p in _builtin_dir().glob("*.toml"))


def library_names() -> list[str]:
    """Names of the built-in non-disc problems (:mod:`hybridoc.problems.library`), sorted."""
    try:
        from hybridoc.problems.library import LIBRARY
    except ImportError:  # pragma: no cover - a partial installation
        return []
    return sorted(LIBRARY)


def load_scene(scene: str | Path | Scene) -> Scene:
    """Load a disc scene from a built-in name, a TOML path, or pass a :class:`Scene` through.

    Raises
    ------
    hybridoc.errors.SceneError
        If the name is unknown, the file cannot be read, or the scene is invalid.
    """
    if isinstance(scene, Scene):
        return scene
    if not isinstance(scene, str | Path):
        raise SceneError(
            f"expected a scene name, a .toml path or a Scene, got {type(scene).__name__}"
        )
    text = str(scene)
    if text in builtin_names():
        return Scene.from_toml(_builtin_dir() / f"{text}.toml")
    path = Path(text)
    if path.suffix == ".toml" or path.exists():
        if not path.exists():
            raise SceneError(f"scene file {text!r} does not exist")
        if path.is_dir():
            raise SceneError(f"scene path {text!r} is a directory, not a .toml file")
        return Scene.from_toml(path)
    raise SceneError(
        f"unknown scene {text!r}: not a built-in ({', '.join(builtin_names())}) "
        "and not a path to a .toml file"
    )


def load_problem(problem: str | Path | Scene | HybridOCP) -> Scene | HybridOCP:
    """A :class:`Scene` or :class:`~hybridoc.HybridOCP` from any name of a problem.

    Parameters
    ----------
    problem
        A built-in scene name, a library problem name (:func:`library_names`), a path to a
        ``.toml`` scene, ``path/to/file.py:function`` (the function takes no arguments and
        returns a HybridOCP or a Scene), or ``path/to/file.py`` with a function ``problem``.
        Scenes and HybridOCPs pass through.

    Raises
    ------
    hybridoc.errors.SceneError
        One line naming what is wrong.
    """
    if not isinstance(problem, str | Path):
        return problem
    text = str(problem)
    if text in builtin_names():
        return load_scene(text)
    if text in library_names():
        return library_ocp(text)
    path_part, _, func = (
        text.partition(":") if ".py:" in text or text.endswith(".py") else (text, "", "")
    )
    if path_part.endswith(".py"):
        return _from_python(Path(path_part), func or "problem", explicit=bool(func))
    try:
        return load_scene(text)
    except SceneError as exc:
        if text.endswith(".toml") or Path(text).exists():
            raise
        names = builtin_names() + library_names()
        raise SceneError(
            f"unknown problem {text!r}: not a built-in ({', '.join(names)}), not a .toml file "
            "and not path/to/file.py:function"
        ) from exc


def library_ocp(name: str) -> HybridOCP:
    """The library problem registered as ``name`` (:func:`library_names`), with its defaults
    and the spec ``{"kind": "library", "name": name}`` that :func:`from_spec` rebuilds it
    from.

    Raises
    ------
    hybridoc.errors.SceneError
        For a name that is not a library problem.
    """
    if not isinstance(name, str) or name not in library_names():
        raise SceneError(
            f"unknown library problem {name!r} (library: {', '.join(library_names())})"
        )
    from hybridoc.problems.library import LIBRARY

    ocp = LIBRARY[name]()
    # a fresh problem: its record gains the spec (its functions are those of the name)
    ocp.capabilities = dataclasses.replace(ocp.capabilities, spec={"kind": "library", "name": name})
    return ocp


def load_spec(spec: Mapping[str, Any]) -> Scene | HybridOCP:
    """What a problem spec names, as :func:`load_problem` gives it: the :class:`Scene` of
    ``{"kind": "scene", "toml": text}`` (with its ``[distribution]`` table), the library
    problem of ``{"kind": "library", "name": name}``. :func:`from_spec` compiles it.

    Raises
    ------
    hybridoc.errors.SceneError
        As :func:`from_spec`.
    """
    if not isinstance(spec, Mapping):
        raise SceneError(f"a problem spec must be a mapping, got {type(spec).__name__}")
    kind = spec.get("kind")
    if kind == "scene":
        text = spec.get("toml")
        if not isinstance(text, str):
            raise SceneError('a scene spec needs its TOML text under "toml"')
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(f"the scene spec is not valid TOML: {exc}") from None
        return Scene.from_dict(data)
    if kind == "library":
        name = spec.get("name")
        if not isinstance(name, str):
            raise SceneError('a library spec needs the problem\'s name under "name"')
        return library_ocp(name)
    raise SceneError(f"unknown problem spec kind {kind!r} (known: scene, library)")


def from_spec(spec: Mapping[str, Any]) -> HybridOCP:
    """Rebuild a problem from its spec (:attr:`Capabilities.spec
    <hybridoc.capabilities.Capabilities.spec>`): the same functions and the data the spec
    was made with.

    Parameters
    ----------
    spec
        ``{"kind": "scene", "toml": text}`` (a disc scene, compiled again) or
        ``{"kind": "library", "name": name}`` (a library problem, looked up in the
        registry). Nothing in a spec is run as code.

    Raises
    ------
    hybridoc.errors.SceneError
        For an unknown kind, a missing or mistyped field, an invalid scene or an unknown
        library name (one line).
    """
    problem = load_spec(spec)
    return problem.to_ocp() if isinstance(problem, Scene) else problem


def spec_of(problem: Scene | HybridOCP) -> Mapping[str, Any] | None:
    """The spec of a problem as it is now (:func:`load_spec` gives it back): a Scene's
    ``{"kind": "scene", "toml": ...}`` without compiling it; a compiled disc problem's, of
    its scene with its current data (a data-only :meth:`~hybridoc.HybridOCP.replace` keeps
    :attr:`Capabilities.spec <hybridoc.capabilities.Capabilities.spec>`, which describes the
    problem as compiled); else the problem's :attr:`Capabilities.spec` (``None`` where it
    has none)."""
    scene = scene_of(problem)
    if scene is not None:
        return {"kind": "scene", "toml": scene.to_toml()}
    return problem.capabilities.spec


def scene_of(problem: Any, *, compiled: bool = True) -> Scene | None:
    """The :class:`Scene` of a disc problem, else ``None``: the one place the layers above
    ``problems/`` ask whether a problem is a disc scene (they import neither class).

    Parameters
    ----------
    problem
        Any object (a name is not loaded: ``None``).
    compiled
        Whether a compiled disc problem (a :class:`DiscOCP`) counts: its scene with its
        current data. ``False``: only a :class:`Scene` itself (for example the source of
        draws from its ``[distribution]`` table).
    """
    if isinstance(problem, Scene):
        return problem
    if compiled and isinstance(problem, DiscOCP):
        return problem.scene
    return None


def _from_python(path: Path, func: str, *, explicit: bool) -> Any:
    from hybridoc.ocp import HybridOCP

    where = f"{str(path)}:{func}"
    module = import_file(path, "problem", SceneError)
    fn = getattr(module, func, None)
    if fn is None:
        hint = "" if explicit else " (name one as file.py:function)"
        raise SceneError(f"{str(path)!r} has no function {func!r}{hint}")
    if not callable(fn):
        raise SceneError(f"{where} is not a function")
    try:
        out = fn()
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(f"{where}() raised {type(exc).__name__}: {exc}") from exc
    except SystemExit as exc:
        raise SceneError(exit_message(where, exc, "instead of returning a problem")) from None
    if not isinstance(out, HybridOCP | Scene):
        raise SceneError(f"{where}() returned {type(out).__name__}, not a HybridOCP or a Scene")
    return out
