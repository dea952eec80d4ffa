"""The registry of library problems: :func:`library_problem` and :data:`LIBRARY`.

A library problem is one module of :mod:`hybridoc.problems.library` whose problem function
carries the decorator; the package imports every one of its modules, so adding a problem
is adding one file.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, TypeVar

__all__ = ["LIBRARY", "NOTES", "library_problem"]

F = TypeVar("F", bound=Callable[..., Any])

LIBRARY: dict[str, Callable[[], Any]] = {}
"""Built-in name (as ``hybridoc problems`` lists it) -> a function returning the problem with
its defaults; other configurations: ``path/to/file.py:function`` or the functions in
Python."""

NOTES: dict[str, str] = {}
"""Built-in name -> what distinguishes it from its function's defaults (for listings)."""


def library_problem(name: str, *, note: str = "", **parameters: Any) -> Callable[[F], F]:
    """Decorator: register a problem function under ``name`` (a built-in problem name).

    Parameters
    ----------
    name
        The built-in name, e.g. ``"bouncing-ball"``; unique.
    note
        A few words for listings when ``parameters`` are given (``"two bounces"``).
    **parameters
        Keyword arguments the name fixes (``bounces=2``); default: the function's defaults.

    Stacking the decorator registers one function under several names.
    """

    def register(fn: F) -> F:
        if name in LIBRARY:
            raise ValueError(f"library problem {name!r} is registered twice")
        LIBRARY[name] = partial(fn, **parameters) if parameters else fn
        if note:
            NOTES[name] = note
        return fn

    return register
