"""The method registry, as :mod:`hybridoc.methods` defines it (kept for older imports).

:func:`solve`, :data:`METHODS`, :class:`Method` and :func:`register_method` are those of
:mod:`hybridoc.methods`, where a method declares its options, tolerance and summary lines;
the built-in methods are its :data:`~hybridoc.methods.BUILTIN` entries.
"""

from __future__ import annotations

from hybridoc.methods import METHODS, Method, register_method, solve

__all__ = ["METHODS", "Method", "register_method", "solve"]
