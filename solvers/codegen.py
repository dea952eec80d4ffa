"""CasADi functions compiled to C in the background, cached on disk, with a fallback.

The solvers' name for :mod:`hybridoc.compiled`, which holds the code cache, its checks and
:class:`Accelerated` (in the model layer since the judge compiles its kernels with it too):
every name here is that module's, the same objects, so that the solvers and the judge share
one cache and one compilation queue.

Settings (environment): ``HYBRIDOC_CODEGEN=0`` turns it off; ``HYBRIDOC_CACHE`` sets the
cache folder (default ``~/.cache/hybridoc``); ``HYBRIDOC_CACHE_MAX_MB`` bounds its size
(default 500; ``0`` keeps no library on disk).
"""

from __future__ import annotations

from hybridoc.compiled import (
    DEFAULT_MAX_MB,
    HOT_CALLS,
    Accelerated,
    CacheWarning,
    NativeFunction,
    cache_dir,
    cache_info,
    cache_limit,
    check_cache_dir,
    clear_cache,
    compiler,
    enabled,
    evict,
)

__all__ = [
    "DEFAULT_MAX_MB",
    "HOT_CALLS",
    "Accelerated",
    "CacheWarning",
    "NativeFunction",
    "cache_dir",
    "cache_info",
    "cache_limit",
    "check_cache_dir",
    "clear_cache",
    "compiler",
    "enabled",
    "evict",
]
