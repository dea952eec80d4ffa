"""``hybridoc cache info`` and ``hybridoc cache clear``: the cache of compiled C code (the
library functions are in :mod:`hybridoc.solvers.codegen`)."""

from __future__ import annotations

import argparse
from typing import Any

from hybridoc.cli._util import emit_json, say, warn

__all__ = ["register"]


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 100_000 else f"{n / 1e3:.1f} kB"


def _info(args: argparse.Namespace) -> int:
    from hybridoc.solvers.codegen import cache_info

    info = cache_info()
    if args.json:
        emit_json(info)
    else:
        if not info["exists"]:
            state = "does not exist yet (made with mode 0700 at the first compilation)"
        elif info["safe"]:
            state = f"{info['mode']}, private (yours, writable by nobody else)"
        else:
            state = f"{info['mode'] or '-'}, NOT private: {info['problem']}"
        unverified = info["unverified"] and (
            f" ({info['unverified']} without a matching record: not loaded, made again)"
        )
        rows = [
            ("path", info["path"]),
            ("permissions", state),
            ("libraries", f"{info['libraries']}{unverified or ''}"),
            ("size", f"{_size(info['size_bytes'])} of {_size(info['limit_bytes'])} at most"),
            ("other files", f"{info['other_files']} (not hybridoc's: never loaded or deleted)"),
            (
                "compilation",
                "on" if info["enabled"] else "off (HYBRIDOC_CODEGEN=0 or no C compiler)",
            ),
        ]
        width = max(len(k) for k, _ in rows)
        for k, v in rows:
            say(args, f"{k.ljust(width)}  {v}")
    if not info["safe"]:
        warn(
            f"the code cache {info['path']!r} is not private: {info['problem']}; no library "
            "is loaded from it, and hybridoc never changes a folder's mode (a shared one must "
            "stay open to its users): 'chmod 700' a folder of your own, or set HYBRIDOC_CACHE "
            "to another folder"
        )
        return 1
    return 0


def _clear(args: argparse.Namespace) -> int:
    from hybridoc.solvers.codegen import clear_cache

    out = clear_cache()
    if args.json:
        emit_json(out)
    else:
        say(
            args,
            f"removed {out['removed']} files ({_size(out['freed_bytes'])}) from {out['path']}; "
            f"other files left: {out['other_files']}",
        )
    return 0


def cmd_cache(args: argparse.Namespace) -> int:
    """Show or empty the cache of C code compiled for gradient descent.

    info: the folder (HYBRIDOC_CACHE, default ~/.cache/hybridoc), whether it is private
    (owned by you and writable by nobody else; otherwise no library is loaded from it and
    the exit code is 1), the number of libraries, their size and the bound
    (HYBRIDOC_CACHE_MAX_MB, default 500). clear: delete the libraries hybridoc compiled and
    their SHA-256 records, and no other file.
    """
    return _info(args) if args.action == "info" else _clear(args)


def register(sub: Any) -> None:
    """Add ``cache``."""
    p = sub.add_parser(
        "cache", help="show or empty the cache of compiled C code", description=cmd_cache.__doc__
    )
    p.add_argument("action", choices=("info", "clear"), help="info: show it; clear: empty it")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_cache)
