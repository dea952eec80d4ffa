"""Import a user's Python file (a problem or a policy) as a fresh module."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from hybridoc.errors import HybridocError

__all__ = ["exit_message", "import_file"]


def import_file(path: Path, kind: str, error: type[HybridocError]) -> ModuleType:
    """Run ``path`` as a module of its own; every failure is one ``error`` naming the file.

    Parameters
    ----------
    path
        The ``.py`` file.
    kind
        What the file holds (``"problem"``, ``"policy"``), for the messages and the module name.
    error
        The error raised for a missing or failing file (one that raises, or calls
        ``sys.exit`` while it is imported); the same error raised by the file's own code
        passes through unchanged.
    """
    if not path.is_file():
        raise error(f"{kind} file {str(path)!r} does not exist")
    name = f"_hybridoc_{kind}_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise error(f"cannot import {str(path)!r}")
    module = importlib.util.module_from_spec(spec)
    # registered before it runs: dataclasses and pickling look their module up by name
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except error:
        del sys.modules[name]
        raise
    except Exception as exc:
        del sys.modules[name]
        raise error(f"importing {str(path)!r} raised {type(exc).__name__}: {exc}") from exc
    except SystemExit as exc:
        # not a way to end hybridoc: exit 0 would read as success with no answer printed
        del sys.modules[name]
        raise error(exit_message(str(path), exc, "while being imported")) from None
    return module


def exit_message(where: str, exc: SystemExit, when: str) -> str:
    """The message of a user's file or function that called ``sys.exit``.

    Parameters
    ----------
    where
        The file or ``file.py:function``.
    exc
        The ``SystemExit`` it raised.
    when
        When, e.g. ``"while being imported"``.
    """
    return (
        f"{where} called sys.exit({exc.code!r}) {when}; a problem or policy file must "
        "return its object (or raise an exception), not end the program"
    )
