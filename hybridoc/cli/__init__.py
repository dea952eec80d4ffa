"""The ``hybridoc`` command: every command in one package.

One module per group of commands (:mod:`.problems`, :mod:`.evaluate`, :mod:`.reference`,
:mod:`.solve`, :mod:`.contacts`, :mod:`.validation`, :mod:`.datasets`, :mod:`.training`,
:mod:`.export`, :mod:`.trajectory`, :mod:`.cache`), each with ``register(subparsers)``; what
they share (arguments, the output convention, exit codes) is in :mod:`._util`. The modules
hold no library code: they parse, call the library, and print.

Building the parser imports no numpy, CasADi, torch, SciPy or matplotlib, so that
``hybridoc --help`` answers at once: the command modules import the library inside their
command functions, and a command whose arguments read a registry adds them on first use
(:meth:`~hybridoc.cli._util.HybridocArgumentParser.defer`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import traceback
import warnings
from collections.abc import Sequence
from typing import Any

from hybridoc.cli._util import HybridocArgumentParser, add_allow_large
from hybridoc.cli.vocabulary import print_notes
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
    "training",
    "contacts",
    "export",
    "trajectory",
    "cache",
)


class _VersionAction(argparse.Action):
    """``--version`` (argparse's, with its help text), reading the installed metadata only
    when asked: importlib.metadata takes tens of milliseconds to import."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        kwargs.setdefault("help", "show program's version number and exit")
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> None:
        from hybridoc import __version__

        print(f"hybridoc {__version__}")
        parser.exit()


def build_parser() -> HybridocArgumentParser:
    """The argument parser with every command (cheap: see the module notes)."""
    parser = HybridocArgumentParser(
        prog="hybridoc",
        description="Optimal control of hybrid systems: an exact reference from the hybrid "
        "minimum principle, solvers (direct transcription, gradient descent through a "
        "differentiable simulation with time-of-impact corrections), and an event-exact judge.",
        epilog="Run 'hybridoc COMMAND --help' for the options of a command.",
    )
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(
        dest="command", metavar="COMMAND", required=True, parser_class=HybridocArgumentParser
    )
    for name in COMMAND_MODULES:
        importlib.import_module(f"hybridoc.cli.{name}").register(sub)
    seen: set[int] = set()
    for command in sub.choices.values():
        if id(command) not in seen:  # an alias shares its command's parser
            seen.add(id(command))
            add_allow_large(command)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code.

    Parameters
    ----------
    argv
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 success, 1 a finding, 2 a user error (or a solver that did not converge), 3 an
        internal error (a bug: any other exception, reported in one line with how to report
        it; ``HYBRIDOC_DEBUG=1`` prints the traceback too), 130 interrupted.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = _run(args)
        except HybridocError as exc:
            print(f"hybridoc: error: {_one_line(exc)}", file=sys.stderr)
            code = 2
        except KeyboardInterrupt:
            print("hybridoc: interrupted", file=sys.stderr)
            code = 130
        except BrokenPipeError:
            # stdout closed early (e.g. piped into head): stop quietly, as other tools do
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            code = 1
        except SystemExit as exc:
            # hybridoc itself never exits inside a command: a user's problem or policy code
            # did (the places that run it turn this into a HybridocError naming the file)
            print(
                f"hybridoc: error: the command was stopped by sys.exit({exc.code!r}) in user "
                "code (a problem or policy file?); no result was produced",
                file=sys.stderr,
            )
            code = 2
        except Exception as exc:
            code = _internal_error(exc)
    _print_warnings(caught)
    if code in (0, 1):  # after a user error its one line stays the only one
        print_notes(args)
    return code


def _run(args: argparse.Namespace) -> int:
    """The command's exit code; with ``--allow-large``, without the memory estimates'
    refusals (:mod:`hybridoc.resources`, imported only then: it is not light)."""
    if not getattr(args, "allow_large", False):
        return int(args.func(args) or 0)
    from hybridoc.resources import allowing_large

    with allowing_large():
        return int(args.func(args) or 0)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _internal_error(exc: Exception) -> int:
    """Report an unexpected exception (a bug in hybridoc, not the user's mistake): exit 3."""
    if os.environ.get("HYBRIDOC_DEBUG", "") not in ("", "0"):
        traceback.print_exception(exc)
    print(f"hybridoc: internal error: {type(exc).__name__}: {_one_line(exc)}", file=sys.stderr)
    print(
        "hybridoc: please report this with the command you ran; HYBRIDOC_DEBUG=1 shows the "
        "traceback",
        file=sys.stderr,
    )
    return 3


def _print_warnings(caught: list[warnings.WarningMessage]) -> None:
    """One line per distinct warning, in order of first appearance, with its count: numpy
    repeats the same RuntimeWarning for every interval of a simulation (1440 lines)."""
    counts: dict[str, int] = {}
    for w in caught:
        # without the internal file and line that Python's default shows
        text = " ".join(str(w.message).split())
        counts[text] = counts.get(text, 0) + 1
    for text, n in counts.items():
        more = f" (repeated {n} times)" if n > 1 else ""
        print(f"hybridoc: warning: {text}{more}", file=sys.stderr)
