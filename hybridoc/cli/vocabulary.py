"""One vocabulary for the ``hybridoc`` command: a concept has one flag in every command.

:data:`VOCABULARY` maps each concept that several commands (or the Python API) share to its
one spelling, the keyword the Python API uses for it, and the old spellings that are kept
for one release as deprecated aliases (hidden from ``--help``; a note on stderr when used).
``tests/test_cli_vocabulary.py`` checks every command against it. The canonical words are
the Python option names, so that ``--set METHOD.OPTION=VALUE``, ``hybridoc solve``'s flags
and ``hybridoc.solve(..., OPTION=VALUE)`` agree.

Building the parser imports this module: it imports nothing but the standard library.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "VOCABULARY",
    "SET_ALIASES",
    "Concept",
    "DeprecatedAlias",
    "DeprecatedSetAlias",
    "add_deprecated_alias",
    "add_deprecated_set_alias",
    "add_set_arg",
    "deprecation_note",
    "print_notes",
    "spelled",
]


@dataclass(frozen=True)
class Concept:
    """One concept of the command line.

    Attributes
    ----------
    flag
        Its one spelling, in every command that has it.
    python
        The keyword of the Python API for it (``None``: the command line only).
    deprecated
        Old spellings, accepted for one release as hidden aliases with a stderr note.
    meaning
        One line: what the flag means, so that a different meaning gets another word.
    """

    flag: str
    python: str | None
    deprecated: tuple[str, ...]
    meaning: str


VOCABULARY: dict[str, Concept] = {
    "controls": Concept(
        "--controls", "initial", ("--initial",),
        "a controls file (.npy, .csv or a saved Solution): the controls judged, or a solver's "
        "start (Python: initial=, which also takes a Solution)",
    ),
    "iterations": Concept(
        "--iters", "iters", ("--gd-iters", "--epochs"),
        "iterations of a descent (gd's, a policy's training), or the iterates compared",
    ),
    "relative tolerance": Concept(
        "--rtol", "rtol", (),
        "the relative tolerance a solve converges to (the reference's shooting)",
    ),
    "residual tolerance": Concept(
        "--tol", "tol", (),
        "the HMP residual a dataset's reference must reach (hybridoc.workflows.datasets)",
    ),
    "terminal tolerance": Concept(
        "--terminal-tol", "terminal_tol", (),
        "the violation of the terminal constraints a solve accepts",
    ),
    "agreement tolerance": Concept(
        "--tolerance", "tolerances", (),
        "crossval: the relative gap within which a method agrees (METHOD=VALUE)",
    ),
    "grid": Concept(
        "--steps", "steps", (),
        "N, the cells of the problem's control grid",
    ),
    "mesh": Concept(
        "--mesh", "mesh", (),
        "the transcription's collocation elements per phase (its own resolution, not N)",
    ),
    "progress": Concept(
        "--no-progress", "progress", (),
        "no progress display on stderr (Python: progress=False)",
    ),
    "verbose": Concept(
        "--verbose", "verbose", (),
        "the reference's search log (a method option; not the progress display)",
    ),
    "contact model": Concept(
        "--contact", "contact", ("--models",),
        "the contact model(s) of the differentiable simulation (gradcheck and "
        "compare-contacts: a list, MODEL or MODEL/TOI)",
    ),
    "time of impact": Concept(
        "--toi", "toi", ("--no-toi",),
        "the time-of-impact corrections of the differentiable simulation: none, position, "
        "velocity or both",
    ),
    "method options": Concept(
        "--set", None, ("--gd-integrator",),
        "a method's option in a workflow: METHOD.OPTION=VALUE (repeatable; the old flags: "
        "SET_ALIASES)",
    ),
    "methods": Concept(
        "--methods", "methods", ("--no-gd",),
        "the registered methods a workflow runs (M,M)",
    ),
    "time limit": Concept(
        "--time-limit", "time_limit", (),
        "seconds a method may run (each method's, in a workflow)",
    ),
    "seed": Concept("--seed", "seed", (), "the seed of random draws"),
    "samples": Concept("--samples", "samples", (), "draws of a problem's distribution"),
    "learning rate": Concept("--lr", "lr", (), "the learning rate of a descent"),
    "substeps": Concept(
        "--substeps", "substeps", (), "rows per grid interval of a controls file"
    ),
}  # fmt: skip
"""The concepts and their one spelling (see the module notes). ``--mesh`` and ``--steps``
are two concepts: the transcription's own resolution and the problem's grid N; so are the
three tolerances (a solve's, a dataset's residual, crossval's agreement)."""


NOTES = "_deprecated"
"""The attribute of the parsed arguments that lists the deprecation notes of the old
spellings used; :func:`hybridoc.cli.main` prints them once the command has run (not after a
user error, whose one line stays the only one)."""


SET_ALIASES: dict[str, dict[str, str]] = {
    "crossval": {"--gd-integrator": "gd.integrator", "--starts": "gd.starts", "--mesh": "dt.mesh"},
}
"""The old flags of one method's option in a workflow command: ``command -> {flag:
"METHOD.OPTION"}``, deprecated spellings of ``--set METHOD.OPTION=VALUE`` (``--starts`` and
``--mesh`` stay the flags of gd's and dt's options in ``hybridoc solve``)."""


def deprecation_note(flag: str, instead: str) -> str:
    """The note for an old spelling: ``flag`` is deprecated, use ``instead``."""
    return f"{flag} is deprecated and will be removed; use {instead}"


def _record(namespace: argparse.Namespace, note: str) -> None:
    notes = list(getattr(namespace, NOTES, None) or [])
    if note not in notes:
        notes.append(note)
    setattr(namespace, NOTES, notes)


def spelled(args: argparse.Namespace, flag: str, *old: str) -> str:
    """How the user spelled ``flag``: the old spelling in ``old`` that was given (its note
    was recorded), else ``flag``; so that an error names the flag as it was typed."""
    notes = getattr(args, NOTES, None) or []
    for spelling in old:
        if any(note.startswith(f"{spelling} ") for note in notes):
            return spelling
    return flag


def print_notes(args: argparse.Namespace) -> None:
    """Print the deprecation notes of ``args`` on stderr, one warning line each."""
    for note in getattr(args, NOTES, None) or []:
        print(f"hybridoc: warning: {note}", file=sys.stderr, flush=True)


class DeprecatedAlias(argparse.Action):
    """An old spelling of another flag: stores into the same ``dest`` (as ``store``,
    ``store_true`` or ``store_false`` would) and records a :func:`deprecation_note`."""

    def __init__(
        self,
        option_strings: Sequence[str],
        dest: str,
        *,
        instead: str,
        const: Any = None,
        nargs: Any = None,
        **kwargs: Any,
    ) -> None:
        self.instead = instead
        kwargs.setdefault("help", argparse.SUPPRESS)
        super().__init__(option_strings, dest, nargs=nargs, const=const, **kwargs)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        _record(namespace, deprecation_note(option_string or self.option_strings[0], self.instead))
        setattr(namespace, self.dest, self.const if self.nargs == 0 else values)


class DeprecatedSetAlias(argparse.Action):
    """An old flag of one method's option: appends ``METHOD.OPTION=VALUE`` to ``--set``'s
    list and records a :func:`deprecation_note`."""

    def __init__(
        self, option_strings: Sequence[str], dest: str, *, setting: str, **kwargs: Any
    ) -> None:
        self.setting = setting
        kwargs.setdefault("help", argparse.SUPPRESS)
        super().__init__(option_strings, dest, **kwargs)

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        flag = option_string or self.option_strings[0]
        _record(namespace, deprecation_note(flag, f"--set {self.setting}={values}"))
        items = list(getattr(namespace, self.dest, None) or [])
        setattr(namespace, self.dest, [*items, f"{self.setting}={values}"])


def add_deprecated_alias(
    parser: argparse.ArgumentParser | Any,
    flag: str,
    *,
    dest: str,
    instead: str,
    switch: bool | None = None,
    **kwargs: Any,
) -> None:
    """Add ``flag`` as a hidden, deprecated spelling of the argument stored in ``dest``.

    Parameters
    ----------
    parser
        The parser (or argument group).
    flag
        The old spelling.
    dest
        The canonical argument's ``dest``.
    instead
        What to use instead, for the note (e.g. ``"--iters K"``).
    switch
        ``True``/``False``: a flag without a value that stores that value; ``None``: a flag
        with a value (``kwargs`` such as ``type``, ``metavar`` as for the canonical one).
    """
    if switch is None:
        parser.add_argument(
            flag, dest=dest, action=DeprecatedAlias, instead=instead,
            default=argparse.SUPPRESS, **kwargs,
        )  # fmt: skip
    else:
        parser.add_argument(
            flag, dest=dest, action=DeprecatedAlias, instead=instead, nargs=0, const=switch,
            default=argparse.SUPPRESS, **kwargs,
        )  # fmt: skip


def add_deprecated_set_alias(
    parser: argparse.ArgumentParser | Any, flag: str, setting: str, **kwargs: Any
) -> None:
    """Add ``flag VALUE`` as a hidden, deprecated spelling of ``--set SETTING=VALUE``
    (``setting``: ``METHOD.OPTION``)."""
    parser.add_argument(
        flag, dest="set", action=DeprecatedSetAlias, setting=setting,
        default=argparse.SUPPRESS, **kwargs,
    )  # fmt: skip


def add_set_arg(parser: argparse.ArgumentParser | Any) -> None:
    """Add ``--set METHOD.OPTION=VALUE`` (repeatable): a method's option in a workflow,
    checked against the registry when the command runs
    (:func:`hybridoc.methods.parse_settings`)."""
    parser.add_argument(
        "--set",
        dest="set",
        action="append",
        default=[],
        metavar="METHOD.OPTION=VALUE",
        help="an option of one method (repeatable), e.g. --set gd.starts=8 --set dt.mesh=16; "
        "the options are those of 'hybridoc solve --method METHOD' (with _ or -)",
    )
