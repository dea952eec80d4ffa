"""What every ``hybridoc`` command shares: arguments, one output convention, exit codes.

Conventions
    * ``PROBLEM`` is a built-in name, a ``.toml`` scene, or ``path/to/file.py:function``.
    * Controls are read from ``.npy``, ``.csv`` or a saved Solution (``.npz``/``.json``).
    * ``--json``: standard output carries exactly one JSON object; everything else goes to
      standard error.
    * ``--out DIR`` writes ``DIR/<problem>_<command>[_<method>]`` + ``.npz``/``.json`` (a
      Solution) or ``.json`` (a report), and ``..._<figure>.png``; a command rerun into the
      same folder replaces its own files and no other command's.
    * Every solving command prints the same block (problem, method, status, cost, events).
    * Exit codes: 0 success (or ``extremal``: the extremal of a sequence the user chose, no
      claim to be the optimum); 1 a finding (a result that is not what it claims to be: not
      optimal, events not as modelled, infeasible, methods that disagree), with a warning
      line; 2 a user error or a solver that did not converge, with one ``error`` line; 3 an
      internal error (a bug), with one ``internal error`` line and how to report it.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc.errors import HybridocError

if TYPE_CHECKING:  # pragma: no cover
    from collections.abc import Mapping

    import numpy as np

    from hybridoc.methods import Method, OptionSpec
    from hybridoc.ocp import HybridOCP
    from hybridoc.problem import ProblemLike

__all__ = [
    "HybridocArgumentParser",
    "add_allow_large",
    "add_controls_arg",
    "add_initial_arg",
    "add_json_out",
    "add_method_options",
    "add_policy_arg",
    "add_progress_arg",
    "add_substeps_arg",
    "check_controls_file",
    "emit_json",
    "ensure_dir",
    "exit_code",
    "fmt",
    "format_table",
    "grid_steps",
    "load_controls_arg",
    "load_substep_controls_arg",
    "load_problem_arg",
    "method_flags",
    "method_options_given",
    "nonnegative_int",
    "option_type",
    "output_stem",
    "positive_float",
    "plain_text",
    "positive_int",
    "print_solution",
    "problem_arg",
    "problem_slug",
    "say",
    "solution_payload",
    "to_jsonable",
    "warn",
]


class HybridocArgumentParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, like every other user error.

    ``hybridoc: error: <command>: <message> (see 'hybridoc <command> --help')`` on stderr and
    exit code 2, instead of argparse's usage block followed by the message.

    A command whose arguments read a registry (methods, contact models, limits of the
    solvers), which imports numpy and CasADi, adds them with :meth:`defer`: they are added
    when the command is first used (parsed, or its help or usage formatted), so that
    ``hybridoc --help`` and the other commands start without those imports, and the
    registries are read after any in-process registration.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._deferred: list[Callable[[HybridocArgumentParser], None]] = []

    def defer(self, add_arguments: Callable[[HybridocArgumentParser], None]) -> None:
        """Call ``add_arguments(self)`` on first use of this parser (see the class notes)."""
        self._deferred.append(add_arguments)

    def complete(self) -> HybridocArgumentParser:
        """Add the deferred arguments now (once); returns the parser."""
        while self._deferred:
            self._deferred.pop(0)(self)
        return self

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self.complete()
        return super().parse_known_args(args, namespace)

    def format_usage(self) -> str:
        self.complete()
        return super().format_usage()

    def format_help(self) -> str:
        self.complete()
        return plain_text(super().format_help())

    def error(self, message: str) -> Any:
        command = self.prog.removeprefix("hybridoc").strip()
        where = f"{command}: " if command else ""
        message = " ".join(message.split())
        self.exit(2, f"hybridoc: error: {where}{message} (see '{self.prog} --help')\n")


def plain_text(text: str) -> str:
    """Help text without reStructuredText markup: roles (``:func:`x```) become their target
    and double back-quoted literals become single-quoted (the command docstrings are also
    the Sphinx pages' text)."""
    text = re.sub(r":[a-z]+:`~?([^`<]+?)(?: <[^`]+>)?`", r"\1", text)
    return re.sub(r"``([^`]+)``", r"'\1'", text)


def option_type(parse: Callable[[str], Any], name: str = "value") -> Callable[[str], Any]:
    """An argparse ``type`` from a parser that raises ``ValueError`` with a one-line reason.

    argparse shows the reason of an ``ArgumentTypeError`` but replaces that of a
    ``ValueError`` by "invalid <type> value": the reason is kept by raising it as an
    ``ArgumentTypeError`` (a :class:`~hybridoc.errors.SceneError` is a ``ValueError`` too).
    """

    def convert(text: str) -> Any:
        try:
            return parse(text)
        except argparse.ArgumentTypeError:
            raise
        except (TypeError, ValueError) as exc:
            raise argparse.ArgumentTypeError(" ".join(str(exc).split()) or repr(text)) from None

    convert.__name__ = name
    return convert


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    from hybridoc.methods import positive_float as parse

    return option_type(parse)(text)


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    from hybridoc.methods import positive_int as parse

    return option_type(parse)(text)


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    from hybridoc.methods import nonnegative_int as parse

    return option_type(parse)(text)


def grid_steps(text: str) -> int:
    """argparse type: a grid size ``N``, an integer from 1 to :data:`hybridoc.ocp.MAX_STEPS`."""
    from hybridoc.ocp import MAX_STEPS

    what = f"an integer >= 1 and at most {MAX_STEPS}"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 1 <= n <= MAX_STEPS:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return n


def to_jsonable(obj: Any) -> Any:
    """Numpy scalars and arrays, tuples, enums and paths -> plain JSON types."""
    from enum import Enum

    import numpy as np

    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, Enum):
        return obj.value
    if isinstance(obj, Path):
        return str(obj)
    return obj


def emit_json(obj: Any) -> None:
    """Print ``obj`` as one JSON object on stdout (floats round-trip exactly)."""
    sys.stdout.write(json.dumps(to_jsonable(obj)) + "\n")
    sys.stdout.flush()


def say(args: argparse.Namespace | None, text: str = "") -> None:
    """Print human text: to stdout normally, to stderr when ``--json`` is on."""
    stream = sys.stderr if getattr(args, "json", False) else sys.stdout
    print(text, file=stream, flush=True)


def warn(text: str) -> None:
    """One warning line on stderr."""
    print(f"hybridoc: warning: {' '.join(str(text).split())}", file=sys.stderr, flush=True)


def problem_arg(parser: argparse.ArgumentParser) -> None:
    """Add the positional ``PROBLEM`` argument."""
    parser.add_argument(
        "problem",
        metavar="PROBLEM",
        help="built-in name (see 'hybridoc problems'), a .toml scene file, or "
        "path/to/file.py:function returning a HybridOCP or a Scene",
    )


def load_problem_arg(text: str) -> Any:
    """The :class:`~hybridoc.HybridOCP` named by a ``PROBLEM`` argument."""
    from hybridoc.problem import as_ocp

    return as_ocp(text)


def disc_scene_of(ocp: HybridOCP, command: str) -> ProblemLike:
    """The scene of a disc problem (:func:`hybridoc.problems.scene_of`), or a one-line error
    naming the command."""
    from hybridoc.problems import scene_of

    scene = scene_of(ocp)
    if scene is None:
        raise HybridocError(f"{command} needs a disc scene; {ocp.name!r} is a generic HybridOCP")
    return scene


def add_allow_large(parser: argparse.ArgumentParser) -> None:
    """Add ``--allow-large`` (every command has it): run sizes whose memory estimate passes
    the limit (:mod:`hybridoc.resources`) instead of refusing them."""
    parser.add_argument(
        "--allow-large",
        action="store_true",
        help="run even when the memory estimate of the sizes asked for (samples, starts, "
        "discs x steps, a file's declared shape) passes the limit: half the available "
        "memory, or HYBRIDOC_MEMORY_LIMIT bytes (HYBRIDOC_ALLOW_LARGE=1 does the same)",
    )


def add_json_out(
    parser: argparse.ArgumentParser, *, out_help: str | None = None, out_required: bool = False
) -> None:
    """Add ``--json`` (one JSON object on stdout) and ``--out DIR`` (required when the files
    are the result, ``out_required``)."""
    parser.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout (messages go to stderr)",
    )
    command = parser.prog.removeprefix("hybridoc").strip() or "command"
    parser.add_argument(
        "--out",
        metavar="DIR",
        type=Path,
        default=None,
        required=out_required,
        help=out_help
        or f"write the results as DIR/<problem>_{command}.json (.npz) and the figures as "
        f"DIR/<problem>_{command}_<figure>.png",
    )


def add_controls_arg(parser: argparse.ArgumentParser) -> None:
    """Add ``--controls FILE``."""
    parser.add_argument(
        "--controls",
        metavar="FILE",
        type=Path,
        default=None,
        help="controls as .npy or .csv (N rows, nu columns) or a saved Solution (.npz/.json); "
        "default: the problem's initial guess",
    )


def add_initial_arg(parser: argparse.ArgumentParser) -> None:
    """Add ``--controls FILE`` as a solver's starting point (``args.initial``); ``--initial``
    is its deprecated alias."""
    from hybridoc.cli.vocabulary import add_deprecated_alias

    parser.add_argument(
        "--controls",
        dest="initial",
        metavar="FILE",
        type=Path,
        default=None,
        help="start from these controls: .npy, .csv or a saved Solution (.npz/.json)",
    )
    add_deprecated_alias(
        parser, "--initial", dest="initial", instead="--controls FILE", type=Path, metavar="FILE"
    )


def _owners_title(owners: Sequence[str]) -> str:
    names = list(owners)
    if len(names) == 1:
        return f"{names[0]} options"
    return f"{', '.join(names[:-1])} and {names[-1]} options"


def method_flags(methods: Mapping[str, Method]) -> dict[str, tuple[OptionSpec, list[str]]]:
    """Every command-line option of the methods: ``name -> (spec, owners)``, where ``spec``
    is the first method's :class:`~hybridoc.methods.OptionSpec` of that name and ``owners``
    every method that takes it, in the registry's order."""
    flags: dict[str, tuple[OptionSpec, list[str]]] = {}
    for name, method in methods.items():
        for spec in method.specs():
            if spec.cli:
                flags.setdefault(spec.name, (spec, []))[1].append(name)
    return flags


def add_method_options(
    parser: argparse.ArgumentParser, methods: Mapping[str, Method], reserved: Sequence[str] = ()
) -> None:
    """Add one flag per command-line option of the methods (:func:`method_flags`).

    The flags of the options that the same methods take form one argument group, titled
    "gd options", "dt and reference options", ...; a flag's help, choices, metavar and
    parser come from the option (:func:`hybridoc.methods.option`), and its default is
    ``None``: :func:`method_options_given` passes on only the flags given. An option whose
    default is ``False`` is a switch (``--verbose``), given without a value.

    Raises
    ------
    TypeError
        An option named like one of ``reserved`` (the command's own arguments).
    """
    groups: dict[tuple[str, ...], list[OptionSpec]] = {}
    for spec, owners in method_flags(methods).values():
        if spec.name in reserved:
            raise TypeError(f"method {owners[0]!r}: option {spec.name!r} is a reserved name")
        groups.setdefault(tuple(owners), []).append(spec)
    for owners, specs in groups.items():
        group = parser.add_argument_group(_owners_title(owners))
        for spec in specs:
            if spec.default is False:  # a switch, off by default: a flag without a value
                group.add_argument(
                    spec.flag, dest=spec.name, action="store_const", const=True, default=None,
                    help=spec.help,
                )  # fmt: skip
                continue
            group.add_argument(
                spec.flag,
                dest=spec.name,
                type=option_type(spec.parser, spec.name),
                choices=spec.choices,
                metavar=spec.metavar,
                default=None,
                help=spec.help,
            )


def method_options_given(
    args: argparse.Namespace, method: str, methods: Mapping[str, Method]
) -> dict[str, Any]:
    """The options given on the command line (:func:`add_method_options`) for ``method``.

    Raises
    ------
    hybridoc.errors.HybridocError
        A flag of an option that ``method`` does not take (one line naming the methods that
        take it).
    """
    flags = method_flags(methods)
    given = {k: getattr(args, k) for k in flags if getattr(args, k, None) is not None}
    wrong = [k for k in given if method not in flags[k][1]]
    if wrong:
        parts = [
            f"{flags[k][0].flag} applies to --method {'/'.join(flags[k][1]) or '-'}" for k in wrong
        ]
        raise HybridocError(f"{'; '.join(parts)}, not to --method {method}")
    return given


def load_controls_arg(path: Path | None, ocp: Any) -> tuple[np.ndarray, str]:
    """Controls from a file (or the initial guess when ``path`` is None) and a label."""
    import numpy as np

    if path is None:
        return np.array(ocp.u_guess, dtype=float), "initial guess"
    from hybridoc.io import load_controls

    check_controls_file(path)
    return load_controls(path, ocp), str(path)


def check_controls_file(path: str | Path) -> None:
    """The sizes a controls file declares, checked before it is read
    (:func:`hybridoc.resources.check_array_file`, :func:`~hybridoc.resources.check_npz_file`):
    a ``.npy`` header claiming more rows than the file holds is a damaged file, and one
    whose array passes the memory limit is refused, both without allocating it."""
    from hybridoc.errors import ControlsError
    from hybridoc.resources import check_array_file, check_npz_file

    where = f"controls file {str(path)!r}"
    if Path(path).suffix.lower() == ".npz":
        check_npz_file(path, where, ControlsError)
    else:
        check_array_file(path, where, ControlsError)


def add_substeps_arg(parser: argparse.ArgumentParser) -> None:
    """Add ``--substeps K`` (the controls file holds ``K`` rows per grid interval)."""
    parser.add_argument(
        "--substeps",
        metavar="K",
        type=positive_int,
        default=None,
        help="the --controls file holds N*K rows, K per grid interval (a simulator's log at K "
        "substeps per control interval, e.g. MuJoCo's ctrl): judge them exactly on the K times "
        "finer grid",
    )


def load_substep_controls_arg(
    path: Path | None, ocp: HybridOCP, substeps: int | None
) -> tuple[HybridOCP, np.ndarray, str]:
    """``(problem, controls, label)`` of ``--controls`` and ``--substeps``: with ``K``
    substeps the problem on the ``K`` times finer grid (:func:`hybridoc.io.substep_problem`)
    and its ``N*K`` rows; without, :func:`load_controls_arg` (whose error for a file of
    ``N*K`` rows names ``--substeps K``)."""
    from hybridoc.io import load_controls, substep_problem

    if path is None:
        if substeps is not None:
            raise HybridocError("--substeps applies to a --controls file (of N*K rows)")
        return (ocp, *load_controls_arg(None, ocp))
    k = 1 if substeps is None else substeps
    check_controls_file(path)
    u = load_controls(path, ocp, substeps=k, flag="--substeps")
    fine = substep_problem(ocp, k)
    label = str(path) if k == 1 else f"{path} ({k} substeps: N = {ocp.steps} x {k})"
    return fine, u, label


def ensure_dir(path: str | Path) -> Path:
    """Create an output directory and check that a file can be created in it, before the
    work (:func:`hybridoc.outputs.check_folder`); an unwritable path is a user error."""
    from hybridoc.outputs import check_folder

    return check_folder(path)


def output_stem(out: Path, problem: str, command: str, method: str | None = None) -> Path:
    """``out/<problem>_<command>[_<method>]``, with a file-safe problem name."""
    parts = [_safe_name(problem), command] + ([method] if method and method != command else [])
    return out / "_".join(parts)


def problem_slug(text: str | Path, ocp: Any) -> str:
    """The file-name slug of a problem in output names: a built-in or library name as it
    was given (``bouncing-ball``, not the problem's long name), otherwise the problem's
    name (``ocp.name``) made file-safe."""
    from hybridoc.problems import builtin_names, library_names

    given = str(text)
    if given in builtin_names() or given in library_names():
        return given
    return _safe_name(str(getattr(ocp, "name", "") or ""))


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "problem"


def add_policy_arg(parser: argparse.ArgumentParser, *, extra: str = "") -> None:
    """Add ``--policy SPEC``, the one flag for a feedback policy."""
    parser.add_argument(
        "--policy",
        metavar="SPEC",
        default=None,
        help="a feedback policy (t, state) -> u: an MLP policy file (policy.json, as "
        "train-policy writes it; runs no code), a TorchScript file (.pt) or "
        "path/to/file.py:name" + extra,
    )


def add_progress_arg(parser: argparse.ArgumentParser) -> None:
    """Add ``--no-progress`` (the progress display on stderr is on by default: a bar on a
    terminal, a plain line every 30 s in a log, :mod:`hybridoc.progress`)."""
    parser.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress display on stderr (default: a bar on a terminal, plain lines in a "
        "log after a minute)",
    )


def fmt(x: float, digits: int = 10) -> str:
    """A float with ``digits`` significant digits (``-`` for NaN or None)."""
    if x is None:
        return "-"
    x = float(x)
    return "-" if math.isnan(x) else f"{x:.{digits}g}"


def format_table(
    headers: Sequence[str], rows: Sequence[Sequence[Any]], *, right: Sequence[bool] | None = None
) -> str:
    """A plain-text table; ``right[k]`` right-aligns column ``k`` (default: numbers)."""
    cells = [[str(c) for c in row] for row in rows]
    widths = [len(h) for h in headers]
    for row in cells:
        widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
    if right is None:
        import numpy as np

        right = [
            all(isinstance(r[k], int | float | np.number) for r in rows) and bool(rows)
            for k in range(len(headers))
        ]

    def line(row: Sequence[str]) -> str:
        parts = [
            c.rjust(w) if r else c.ljust(w) for c, w, r in zip(row, widths, right, strict=True)
        ]
        return "  ".join(parts).rstrip()

    out = [line(list(headers)), line(["-" * w for w in widths])]
    out += [line(row) for row in cells]
    return "\n".join(out)


def events_table(events: Sequence[dict[str, Any]]) -> str:
    """The events of a Solution or an Evaluation as a table."""
    rows = [
        [k, repr(float(e["time"])), e.get("guard") or "|".join(e["bodies"]), e["kind"]]
        for k, e in enumerate(events, start=1)
    ]
    if events and all("mode_before" in e for e in events):  # a problem with modes
        for row, e in zip(rows, events, strict=True):
            row.append(f"{e['mode_before']} -> {e['mode_after']}")
        headers = ["#", "time", "transition", "kind", "modes"]
        return format_table(headers, rows, right=[True, False, False, False, False])
    return format_table(["#", "time", "guard", "kind"], rows, right=[True, False, False, False])


def indent(text: str, prefix: str = "  ") -> str:
    """Every line of ``text`` indented."""
    return "\n".join(prefix + line for line in text.splitlines())


def solution_payload(sol: Any, **extra: Any) -> dict[str, Any]:
    """The one JSON shape of a solving command's answer."""
    out = {
        "problem": sol.scene,
        "method": sol.method,
        "status": sol.status.value,
        "success": sol.success,
        "message": sol.message,
        "cost": sol.cost,
        "terminal_cost": sol.terminal_cost,
        "running_cost": sol.running_cost,
        "events": sol.events,
        "sequence": sol.sequence,
        "timings": sol.timings,
        "settings": sol.settings,
        "info": sol.info,
    }
    out.update(extra)
    return out


def print_solution(
    args: argparse.Namespace, sol: Any, ocp: Any, details: Sequence[tuple[str, str]] = ()
) -> None:
    """The one human-readable block of a solving command's answer."""
    horizon = f"T = {fmt(ocp.horizon)}"
    if ocp.free_horizon and sol.info.get("horizon") is not None:
        lo, hi = ocp.horizon_bounds
        horizon = f"T = {fmt(sol.info['horizon'])} found in [{fmt(lo)}, {fmt(hi)}]"
    rows = [
        ("problem", f"{ocp.name} (N = {ocp.steps}, {horizon})"),
        ("method", sol.method),
        ("status", sol.status.value + (f": {sol.message}" if sol.message else "")),
        ("cost", repr(float(sol.cost))),
        ("terminal", repr(float(sol.terminal_cost))),
        ("running", repr(float(sol.running_cost))),
        *details,
    ]
    t = sol.timings.get("solve_time_s", sol.timings.get("wall_time_s"))
    if t is not None:
        rows.append(("time", f"{float(t):.3g} s"))
    rows.append(("events", str(len(sol.events))))
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        say(args, f"{k.ljust(width)}  {v}")
    if sol.events:
        say(args, indent(events_table(sol.events)))


def exit_code(status: Any, message: str = "") -> int:
    """The exit code of a status (module notes), printing the warning line of a finding
    (an ``extremal``, exit 0, says what it is in the printed status line instead)."""
    from hybridoc.solution import Status

    st = Status(status)
    if st.exit_code != 0:
        text = f"{st.value}: {message}" if message else st.value
        if st.exit_code == 2:
            print(f"hybridoc: error: {' '.join(text.split())}", file=sys.stderr, flush=True)
        else:
            warn(text)
    return st.exit_code
