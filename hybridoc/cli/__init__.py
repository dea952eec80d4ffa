"""The ``hybridoc`` command: every command in one package.

One module per group of commands (:mod:`.problems`, :mod:`.evaluate`, :mod:`.reference`,
:mod:`.solve`, :mod:`.contacts`, :mod:`.validation`, :mod:`.datasets`), each with
``register(subparsers)``; what they share (arguments, the output convention, exit codes) is
in :mod:`._util`. The modules hold no library code: they parse, call the library, and print.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from collections.abc import Sequence

from hybridoc.cli._util import HybridocArgumentParser
from hybridoc.errors import HybridocError

__all__ = ["COMMAND_MODULES", "build_parser", "main"]

#: The command modules, in the order their commands are listed.
COMMAND_MODULES = (
    "problems",
    "evaluate",
    "reference",
    "solve",
    "validation",
    "datasets",
    "contacts",
    "cache",
)


def build_parser() -> HybridocArgumentParser:
    """The argument parser with every command."""
    from hybridoc import __version__

    parser = HybridocArgumentParser(
        prog="hybridoc",
        description="Optimal control of hybrid systems: an exact reference from the hybrid "
        "minimum principle, solvers (direct transcription, gradient descent through a "
        "differentiable simulation with time-of-impact corrections), and an event-exact judge.",
        epilog="Run 'hybridoc COMMAND --help' for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"hybridoc {__version__}")
    sub = parser.add_subparsers(
        dest="command", metavar="COMMAND", required=True, parser_class=HybridocArgumentParser
    )
    for name in COMMAND_MODULES:
        importlib.import_module(f"hybridoc.cli.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code.

    Parameters
    ----------
    argv
        Arguments without the program name; default ``sys.argv[1:]``.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = int(args.func(args) or 0)
        except HybridocError as exc:
            message = " ".join(str(exc).split()) or type(exc).__name__
            print(f"hybridoc: error: {message}", file=sys.stderr)
            code = 2
        except KeyboardInterrupt:
            print("hybridoc: interrupted", file=sys.stderr)
            code = 130
        except BrokenPipeError:
            # stdout closed early (e.g. piped into head): stop quietly, as other tools do
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            code = 1
    for w in caught:
        # one line each, without the internal file and line that Python's default shows
        print(f"hybridoc: warning: {' '.join(str(w.message).split())}", file=sys.stderr)
    return code
