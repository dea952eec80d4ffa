"""Operations that a model-layer type offers and a higher layer implements.

The :class:`~hybridoc.solution.Solution` is data plus its file format (the model layer,
docs/architecture.rst): judging it, projecting it on a grid, sampling it and rebuilding the
reference's HMP control law need the judge, the problems and the reference, all above it.
Its methods of those names delegate, in one line each, to the implementation this registry
hands them: the model layer names no higher module, neither by an import nor by a
``"module:attribute"`` string.

Who fills the registry is visible to the import graph (``tests/test_architecture.py``): the
package itself (``hybridoc/__init__.py``, the api layer above every other) registers, when
``hybridoc`` is imported (always before any of its modules), one loader per slot, a
function that imports the implementing module and returns what the slot names. The loader
runs on the slot's first use, so ``import hybridoc`` stays free of numpy.

Slots
-----
``"judging"``
    The module :mod:`hybridoc.judging` (the Solution's control function, judge, grid
    projection and samples).
``"control-law:<kind>"``
    ``(solution, problem) -> (u, breakpoints)``: a control kind that only a higher layer can
    rebuild; ``"control-law:hmp"`` is the reference's HMP control law of a generic problem
    (:func:`hybridoc.reference.result.hmp_control`).

This module imports nothing but :mod:`hybridoc.errors`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hybridoc.errors import HybridocError

__all__ = ["provide", "provider", "register"]

_LOADERS: dict[str, Callable[[], Any]] = {}
_PROVIDED: dict[str, Any] = {}


def register(slot: str, loader: Callable[[], Any]) -> None:
    """Register the loader of ``slot``: called on the slot's first use, it imports the
    implementing module and returns the implementation. A later registration replaces it
    (and forgets what the former loader gave).

    Parameters
    ----------
    slot
        The slot's name, e.g. ``"judging"`` or ``"control-law:hmp"``.
    loader
        A function of no arguments returning the implementation.
    """
    _LOADERS[slot] = loader
    _PROVIDED.pop(slot, None)


def provide(slot: str, implementation: Any) -> None:
    """Set the implementation of ``slot`` directly (a plugin's control law, a test's double).

    Parameters
    ----------
    slot
        The slot's name.
    implementation
        What :func:`provider` returns for it from now on.
    """
    _PROVIDED[slot] = implementation


def provider(slot: str) -> Any:
    """The implementation of ``slot``, loaded on first use.

    Raises
    ------
    hybridoc.errors.HybridocError
        No loader or implementation is registered for ``slot``.
    """
    try:
        return _PROVIDED[slot]
    except KeyError:
        pass
    loader = _LOADERS.get(slot)
    if loader is None:
        raise HybridocError(
            f"nothing provides {slot!r} (known: {sorted(set(_LOADERS) | set(_PROVIDED))})"
        )
    implementation = loader()
    _PROVIDED[slot] = implementation
    return implementation
