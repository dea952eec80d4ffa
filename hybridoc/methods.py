"""What a solver is: :class:`Method`, its typed options (:func:`option`), and the registry.

A method is one module that defines a run function, a dataclass of its options and a
``METHOD = Method(...)`` that ties them together, plus one registration line
(:func:`register_method`, or an entry of :data:`BUILTIN` for the methods that ship with
hybridoc). Everything that treats methods generally reads the :class:`Method`:

* ``hybridoc.solve(problem, method, **options)`` checks the options against
  :attr:`Method.options`;
* ``hybridoc solve`` builds one flag per option field (its help, choices and parser come
  from the field's :func:`option` metadata) and prints :attr:`Method.summary_lines`;
* ``crossval`` reads :attr:`Method.tolerance`, :attr:`Method.crossval_defaults`,
  :attr:`Method.crossval_check`, :attr:`Method.representation` (what its control can
  express, hence what it is measured against), :attr:`Method.resolution_option` and
  :attr:`Method.check_options`; ``convergence`` and the learning-curve figures read
  :attr:`Method.representation` and :attr:`Method.loss_history`;
* ``hybridoc crossval --set METHOD.OPTION=VALUE`` is parsed by :func:`parse_settings`
  against :attr:`Method.options`.

None of them names a method. The contract of a method's ``run``:
``run(ocp, *, initial=None, progress=None, **options) -> Solution``, where ``ocp`` is a
:class:`~hybridoc.HybridOCP`, ``initial`` the initial guess (``None``, ``(N, nu)`` controls or
a Solution), ``progress`` a :data:`~hybridoc.progress.ProgressLike` and ``options`` the
fields of :attr:`Method.options`. It raises :class:`~hybridoc.errors.HybridocError`
subclasses for user errors and returns a :class:`~hybridoc.solution.Solution` whose cost is
the judge's cost of its control and whose status says what the result is.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

from hybridoc import tolerances
from hybridoc.errors import OptionError, SceneError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from hybridoc.ocp import HybridOCP
    from hybridoc.problem import ControlsLike, ProblemLike
    from hybridoc.progress import ProgressLike
    from hybridoc.solution import Solution

_O = TypeVar("_O")

__all__ = [
    "BUILTIN",
    "BUILTIN_SOURCES",
    "CLI_METHOD",
    "DEFAULT_METHOD",
    "DEFAULT_TOLERANCE",
    "FEATURES",
    "METHODS",
    "REFERENCE_METHOD",
    "RUN_KEYWORDS",
    "Method",
    "NoOptions",
    "OptionSpec",
    "REPRESENTATIONS",
    "get_method",
    "loss_history",
    "load_builtin_sources",
    "nonnegative_int",
    "option",
    "option_specs",
    "options_from_keywords",
    "options_signature",
    "parse_bool",
    "parse_setting",
    "parse_settings",
    "positive_float",
    "positive_int",
    "problem_features",
    "register_method",
    "settings_lines",
    "solve",
    "unregister_method",
]

DEFAULT_TOLERANCE = tolerances.CROSSVAL
"""Relative cost gap to the reference within which a method agrees with it in crossval,
unless the method declares its own (:attr:`Method.tolerance`)."""

FEATURES: dict[str, str] = {
    "terminal": "terminal constraints",
    "free_horizon": "a free final time",
}
"""Problem features a method may or may not honour (:attr:`Method.features`), with the
words :func:`solve` uses when it refuses a problem."""


def problem_features(ocp: HybridOCP) -> list[str]:
    """The :data:`FEATURES` a problem has."""
    out = []
    if ocp.has_terminal_constraints or ocp.final_mode is not None:
        out.append("terminal")
    if ocp.horizon_bounds is not None:
        out.append("free_horizon")
    return out


REPRESENTATIONS: dict[str, str] = {
    "grid": "a control held constant on each cell of the problem's N-step grid; its events "
    "fall wherever the dynamics put them",
    "continuous": "a continuous-time control of the method's own discretisation, with the "
    "event times among its unknowns: its cost does not depend on the problem's N",
}
"""What a method's control can express (:attr:`Method.representation`), and so what the
workflows measure it against: crossval projects the reference onto the grid (cell
averages) for ``"grid"``, and re-solves the method from the reference for ``"continuous"``;
convergence re-runs a ``"grid"`` method at each N and averages a ``"continuous"`` one's
control on each grid."""

RUN_KEYWORDS = ("initial", "progress")
"""Keywords every method's ``run`` takes besides its options."""

REFERENCE_METHOD = "reference"
"""The ground truth: the method the workflows (crossval, convergence, validate) measure the
others against."""

DEFAULT_METHOD = REFERENCE_METHOD
"""The method :func:`solve` runs when none is named (the ground truth)."""

CLI_METHOD = "gd"
"""The method ``hybridoc solve`` runs without ``--method`` (the quick one)."""


# ------------------------------------------------------------- parsers of option values
def _number(text: str, kind: type, test: Callable[[Any], bool], what: str) -> Any:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise ValueError(f"expected {what}, got {text!r}") from None
    if not test(value):
        raise ValueError(f"expected {what}, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """Parse a finite number > 0 (a ``parse=`` of :func:`option`); ``ValueError`` otherwise."""
    return _number(text, float, lambda x: math.isfinite(x) and x > 0, "a finite number > 0")


def positive_int(text: str) -> int:
    """Parse an integer >= 1 (a ``parse=`` of :func:`option`); ``ValueError`` otherwise."""
    return _number(text, int, lambda n: n >= 1, "an integer >= 1")


def nonnegative_int(text: str) -> int:
    """Parse an integer >= 0 (a ``parse=`` of :func:`option`); ``ValueError`` otherwise."""
    return _number(text, int, lambda n: n >= 0, "an integer >= 0")


def _finite_float(text: str) -> float:
    return _number(text, float, math.isfinite, "a finite number")


def _integer(text: str) -> int:
    return _number(text, int, lambda n: True, "an integer")


def parse_bool(text: str) -> bool:
    """Parse ``yes``/``no``, ``true``/``false``, ``on``/``off`` or ``1``/``0`` (any case).

    Raises
    ------
    ValueError
        For any other text.
    """
    word = str(text).strip().lower()
    if word in ("yes", "true", "on", "1"):
        return True
    if word in ("no", "false", "off", "0"):
        return False
    raise ValueError(f"expected yes or no, got {text!r}")


def option(
    default: Any,
    help: str,
    *,
    choices: Sequence[Any] | Callable[[], Sequence[Any]] | None = None,
    parse: Callable[[str], Any] | None = None,
    metavar: str | None = None,
    cli: bool = True,
) -> Any:
    """A field of a method's options dataclass, with what the CLI needs to offer it.

    Parameters
    ----------
    default
        The default value (``None``: the method decides, and says so in ``help``).
    help
        One line for ``hybridoc solve --help`` and the documentation.
    choices
        The allowed values, or a function returning them (read when the flags are built, so
        that a registry of contact models, say, is imported only then).
    parse
        Turns the command-line text into the value and raises ``ValueError`` (or
        ``argparse.ArgumentTypeError``) with a one-line reason (:func:`positive_float`,
        :func:`positive_int`, :func:`nonnegative_int`, :func:`parse_bool` or the method's
        own); default: by the type of ``default`` (:attr:`OptionSpec.parser`).
    metavar
        The placeholder in ``--help``.
    cli
        ``False`` for options that only the Python API can pass (callbacks, objects).
    """
    meta = {
        "help": help,
        "choices": choices,
        "parse": parse,
        "metavar": metavar,
        "cli": cli,
    }
    if isinstance(default, list | dict | set):
        raise TypeError("option defaults must be immutable (a tuple, not a list)")
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class OptionSpec:
    """One option of a method, as the CLI and the docs see it (:func:`option_specs`)."""

    name: str
    default: Any
    help: str
    choices: tuple[Any, ...] | None
    parse: Callable[[str], Any] | None
    metavar: str | None
    cli: bool

    @property
    def flag(self) -> str:
        """The command-line flag, e.g. ``--time-limit``."""
        return "--" + self.name.replace("_", "-")

    @property
    def parser(self) -> Callable[[str], Any]:
        """What turns the command-line text into the value: ``parse``, or by the type of the
        default (:func:`parse_bool` for a bool, an integer or a finite number for a number,
        the text itself otherwise)."""
        if self.parse is not None:
            return self.parse
        if isinstance(self.default, bool):
            return parse_bool
        if isinstance(self.default, int):
            return _integer
        if isinstance(self.default, float):
            return _finite_float
        return str


def options_signature(run: Callable[..., Any], options: type) -> inspect.Signature:
    """``run``'s signature with its ``**options`` spelled out as the keyword-only fields of
    the dataclass ``options``, with their defaults.

    A method's public function is a thin wrapper ``run(problem, *, initial=None,
    progress=None, **options)`` that builds its options dataclass; setting
    ``run.__signature__ = options_signature(run, Options)`` shows :func:`inspect.signature`,
    the documentation and :meth:`Method.check_signature` every option with its default,
    while the defaults stay written once, in the dataclass."""
    sig = inspect.signature(run)
    params = [p for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD]
    params += [
        inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default,
                          annotation=f.type)
        for f in dataclasses.fields(options)
    ]  # fmt: skip
    return sig.replace(parameters=params)


def options_from_keywords(options: type[_O], keywords: Mapping[str, Any], caller: str) -> _O:
    """The options dataclass of a thin wrapper (:func:`options_signature`), built from its
    keywords.

    A keyword that is no field raises Python's own ``TypeError``, as a function with those
    keyword parameters would; the dataclass's checks raise
    :class:`~hybridoc.errors.OptionError` for bad values."""
    names = {f.name for f in dataclasses.fields(options)}
    unknown = [k for k in keywords if k not in names]
    if unknown:
        raise TypeError(f"{caller}() got an unexpected keyword argument {unknown[0]!r}")
    return options(**keywords)


def option_specs(options: type) -> list[OptionSpec]:
    """The :class:`OptionSpec` of every field of an options dataclass, in order."""
    out = []
    for f in dataclasses.fields(options):
        meta = f.metadata
        choices = meta.get("choices")
        if callable(choices):
            choices = choices()
        out.append(
            OptionSpec(
                name=f.name,
                default=f.default,
                help=meta.get("help", ""),
                choices=None if choices is None else tuple(choices),
                parse=meta.get("parse"),
                metavar=meta.get("metavar"),
                cli=meta.get("cli", True),
            )
        )
    return out


@dataclass(frozen=True)
class NoOptions:
    """The options of a method that takes none."""


def loss_history(sol: Solution) -> np.ndarray | None:
    """The default :attr:`Method.loss_history`: ``sol.arrays["loss_history"]`` (the loss at
    each iteration, as gradient descent stores it), ``None`` when it is absent or empty."""
    hist = sol.arrays.get("loss_history")
    if hist is None or not len(hist):
        return None
    return hist


def settings_lines(sol: Solution) -> list[tuple[str, str]]:
    """The default :attr:`Method.summary_lines`: one ``("settings", "k v, ...")`` line of
    ``sol.settings`` (none when it is empty); a method's own summary ends with it."""
    settings = ", ".join(f"{k} {v}" for k, v in sol.settings.items() if v is not None)
    return [("settings", settings)] if settings else []


@dataclass(frozen=True)
class Method:
    """A registered solver and everything about it.

    Attributes
    ----------
    name
        The ``method=`` value and ``--method`` choice.
    summary
        One line for listings and ``--help``.
    run
        ``run(ocp, *, initial=None, progress=None, **options) -> Solution`` (module notes),
        or ``"module:function"`` naming it, imported on first use.
    options
        A frozen dataclass whose fields, made with :func:`option`, are the method's options
        (the keywords of ``run`` besides :data:`RUN_KEYWORDS`).
    tolerance
        Relative cost gap to the reference within which crossval says the method agrees.
    supports
        ``supports(ocp) -> None`` when the method can solve the problem, else a one-line
        reason.
    summary_lines
        ``summary_lines(sol) -> [(label, text), ...]``: what ``hybridoc solve`` prints about
        a solution besides status, cost and events.
    crossval_defaults
        ``crossval_defaults(ocp, options) -> options``: the options crossval runs the method
        with when the caller sets none (gd's multi-start, say); default: as given.
    crossval_check
        ``crossval_check(ocp, sol) -> (entry, reasons)``: a method's own check in crossval
        (fields added to its report entry, and the reasons it disagrees); default: none.
    features
        The problem features beyond the basic model that the method honours, from
        :data:`FEATURES` (``"terminal"``: terminal constraints; ``"free_horizon"``: a free
        final time). :func:`solve` refuses a problem with a feature its method lacks, so
        that a method never answers a problem it silently simplified.
    representation
        What the method's control can express, a key of :data:`REPRESENTATIONS`:
        ``"grid"`` (default: piecewise constant on the problem's N-step grid) or
        ``"continuous"`` (its own discretisation, with the event times as unknowns).
    resolution_option
        For a ``"continuous"`` method, the option that sets its own resolution (the
        transcription's ``mesh``): crossval's refinement check doubles it, starting from the
        value the Solution reports in ``info`` (or ``settings``) under the same name;
        ``None`` for a method whose resolution is the problem's grid.
    projection_options
        The options a ``"continuous"`` method keeps when crossval re-solves it from the
        reference (the transcription: ``mesh`` and ``degree``); the reference's event
        sequence is passed as ``sequence`` when the method takes that option.
    loss_history
        ``loss_history(sol) -> array | None``: the method's loss at each iteration, drawn as
        a learning curve (:func:`loss_history`: ``sol.arrays["loss_history"]``).
    check_options
        ``check_options(ocp, options) -> Any``, ``options`` an instance of :attr:`options`:
        the check the method's run makes of its options first, raising a
        :class:`~hybridoc.errors.HybridocError` (a size beyond the memory limit, say);
        ``hybridoc crossval`` calls it before any method runs. ``None``: no early check.
    """

    name: str
    summary: str
    run: Callable[..., Solution] | str
    options: type = NoOptions
    tolerance: float = DEFAULT_TOLERANCE
    supports: Callable[[HybridOCP], str | None] = field(default=lambda ocp: None)
    summary_lines: Callable[[Solution], list[tuple[str, str]]] = settings_lines
    crossval_defaults: Callable[[HybridOCP, dict[str, Any]], dict[str, Any]] | None = None
    crossval_check: Callable[[HybridOCP, Solution], tuple[dict[str, Any], list[str]]] | None = None
    features: frozenset[str] = frozenset()
    representation: str = "grid"
    resolution_option: str | None = None
    projection_options: tuple[str, ...] = ()
    loss_history: Callable[[Solution], np.ndarray | None] = loss_history
    check_options: Callable[[HybridOCP, Any], Any] | None = None

    def __post_init__(self) -> None:
        if not dataclasses.is_dataclass(self.options):
            raise TypeError(f"method {self.name!r}: options must be a dataclass")
        unknown = set(self.features) - set(FEATURES)
        if unknown:
            raise TypeError(f"method {self.name!r}: unknown features {sorted(unknown)}")
        if self.representation not in REPRESENTATIONS:
            raise TypeError(
                f"method {self.name!r}: representation must be one of {sorted(REPRESENTATIONS)}"
            )
        names = self.option_names()
        for opt in (self.resolution_option, *self.projection_options):
            if opt is not None and opt not in names:
                raise TypeError(f"method {self.name!r}: {opt!r} is not one of its options")

    def takes(self, option: str) -> bool:
        """Whether ``option`` is one of the method's options."""
        return option in self.option_names()

    def checked(self, ocp: HybridOCP, options: Mapping[str, Any]) -> None:
        """Run :attr:`check_options` on ``options`` (a mapping of option values), when the
        method has one."""
        if self.check_options is not None:
            self.check_options(ocp, self.options(**options))

    def missing_features(self, ocp: HybridOCP) -> list[str]:
        """The features of ``ocp`` (:func:`problem_features`) this method does not honour."""
        return [f for f in problem_features(ocp) if f not in self.features]

    def function(self) -> Callable[..., Solution]:
        """The run function."""
        if callable(self.run):
            return self.run
        module, _, attr = self.run.partition(":")
        return getattr(importlib.import_module(module), attr)

    def option_names(self) -> tuple[str, ...]:
        """The names of the method's options."""
        return tuple(f.name for f in dataclasses.fields(self.options))

    def accepted(self) -> tuple[str, ...]:
        """Every keyword ``run`` accepts: :data:`RUN_KEYWORDS` and the options."""
        return RUN_KEYWORDS + self.option_names()

    def specs(self) -> list[OptionSpec]:
        """The options as :class:`OptionSpec` (:func:`option_specs`)."""
        return option_specs(self.options)

    def check_signature(self) -> None:
        """Raise ``TypeError`` unless ``run`` takes ``ocp`` and exactly :meth:`accepted` as
        keywords (the conformance test runs this on every registered method)."""
        params = inspect.signature(self.function()).parameters
        taken = {
            p.name
            for p in list(params.values())[1:]
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD) and not p.name.startswith("_")
        }
        if taken != set(self.accepted()):
            raise TypeError(
                f"method {self.name!r}: run takes {sorted(taken)}, options and run keywords "
                f"are {sorted(self.accepted())}"
            )


BUILTIN: dict[str, str] = {
    "reference": "hybridoc.reference.solve:METHOD",
    "dt": "hybridoc.solvers.transcription:METHOD",
    "gd": "hybridoc.solvers.gd:METHOD",
}
"""The methods that ship with hybridoc: ``name -> "module:attribute"`` of their
:class:`Method`, imported on first use."""


BUILTIN_SOURCES: tuple[str, ...] = ("hybridoc.solvers.candidates:register_builtin_sources",)
"""Functions (``"module:function"``) that register the reference's candidate sources that
ship with hybridoc (the transcription, the multi-start): the reference's registry calls them
on first use (:func:`load_builtin_sources`), as :data:`BUILTIN` names the built-in methods,
so that the reference runs with them however it is reached and still imports no solver."""

_SOURCES_LOADED = False


def load_builtin_sources() -> None:
    """Call the :data:`BUILTIN_SOURCES` registration functions (once per process)."""
    global _SOURCES_LOADED
    if _SOURCES_LOADED:
        return
    _SOURCES_LOADED = True
    for where in BUILTIN_SOURCES:
        module, _, attr = where.partition(":")
        getattr(importlib.import_module(module), attr)()


class _Registry(Mapping[str, Method]):
    """The registered methods by name; built-in ones are imported when first looked up."""

    def __init__(self) -> None:
        self._lazy: dict[str, str] = dict(BUILTIN)
        self._loaded: dict[str, Method] = {}

    def __getitem__(self, name: str) -> Method:
        if name in self._loaded:
            return self._loaded[name]
        where = self._lazy[name]  # KeyError for an unknown name, as a Mapping should
        module, _, attr = where.partition(":")
        method = getattr(importlib.import_module(module), attr)
        if not isinstance(method, Method) or method.name != name:
            raise TypeError(f"{where} is not the Method {name!r}")
        self._loaded[name] = method
        return method

    def __contains__(self, name: object) -> bool:
        return name in self._lazy or name in self._loaded

    def __iter__(self) -> Iterator[str]:
        return iter(dict.fromkeys([*self._lazy, *self._loaded]))

    def __len__(self) -> int:
        return len(set(self._lazy) | set(self._loaded))

    def add(self, method: Method) -> None:
        self._lazy.pop(method.name, None)
        self._loaded[method.name] = method

    def remove(self, name: str) -> None:
        if name not in self:
            raise KeyError(name)
        self._lazy.pop(name, None)
        self._loaded.pop(name, None)


METHODS = _Registry()
"""Every registered method, by name (a read-only mapping; :func:`register_method` adds)."""


def register_method(method: Method) -> Method:
    """Add a method to :data:`METHODS`, replacing one of the same name; returns it."""
    if not isinstance(method, Method):
        raise TypeError(f"register_method takes a Method, got {type(method).__name__}")
    METHODS.add(method)
    return method


def unregister_method(name: str) -> None:
    """Remove the method called ``name`` from :data:`METHODS` (a test's or a plugin's);
    ``KeyError`` when there is none. A built-in one comes back with :func:`register_method`
    of its ``METHOD``."""
    METHODS.remove(name)


def get_method(name: str) -> Method:
    """The registered method called ``name``.

    Raises
    ------
    hybridoc.errors.OptionError
        For an unknown name (one line listing the registered ones).
    """
    if not isinstance(name, str) or name not in METHODS:
        raise OptionError(f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return METHODS[name]


def parse_setting(text: str) -> tuple[str, str, Any]:
    """One ``METHOD.OPTION=VALUE`` of ``--set``, checked against the registry.

    The value is parsed by the option's parser (:attr:`OptionSpec.parser`) and checked
    against its choices, as the option's own flag of ``hybridoc solve`` would be.

    Returns
    -------
    tuple
        ``(method, option, value)``.

    Raises
    ------
    hybridoc.errors.OptionError
        Text not of that form, an unknown method or option (one line naming the valid
        ones), an option only the Python API takes, or a value its parser refuses.
    """
    head, sep, raw = str(text).partition("=")
    method, dot, name = head.strip().partition(".")
    if not sep or not dot or not method or not name.strip():
        raise OptionError(f"--set expects METHOD.OPTION=VALUE (e.g. gd.starts=8), got {text!r}")
    name = name.strip().replace("-", "_")
    if method not in METHODS:
        raise OptionError(
            f"--set {text}: unknown method {method!r}; choose one of {', '.join(METHODS)}"
        )
    specs = {s.name: s for s in METHODS[method].specs() if s.cli}
    if name not in specs:
        takes = ", ".join(specs) or "none"
        raise OptionError(f"--set {text}: {method} has no option {name!r}; it takes {takes}")
    spec = specs[name]
    try:
        value = spec.parser(raw.strip())
    except (TypeError, ValueError) as exc:
        raise OptionError(f"--set {text}: {' '.join(str(exc).split())}") from None
    if spec.choices is not None and value not in spec.choices:
        choices = ", ".join(map(str, spec.choices))
        raise OptionError(f"--set {text}: {name} must be one of {choices}")
    return method, name, value


def parse_settings(items: Sequence[str] | None) -> dict[str, dict[str, Any]]:
    """``--set`` items (:func:`parse_setting`) as ``{method: {option: value}}``; a later
    item of the same option wins, as a repeated flag does."""
    out: dict[str, dict[str, Any]] = {}
    for text in items or ():
        method, name, value = parse_setting(text)
        out.setdefault(method, {})[name] = value
    return out


def solve(
    problem: ProblemLike,
    method: str = DEFAULT_METHOD,
    *,
    initial: ControlsLike | None = None,
    progress: ProgressLike = None,
    **options: Any,
) -> Solution:
    """Solve a problem with a registered method.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`): a built-in name, a ``.toml`` file,
        ``file.py:function``, a Scene or a HybridOCP.
    method
        ``"reference"`` (HMP shooting), ``"dt"`` (direct transcription), ``"gd"`` (gradient
        descent through the differentiable simulation), or any method registered later
        (:data:`METHODS`).
    initial
        The initial guess: ``None`` (the problem's), ``(N, nu)`` controls or a Solution.
    progress
        ``None``/``False`` (silent), ``True`` (a meter on stderr) or a
        :class:`~hybridoc.progress.Progress`.
    **options
        The method's options: the fields of ``METHODS[method].options``.

    Returns
    -------
    Solution
        With ``status``, ``success``, ``message``, the judge's ``cost`` and ``events``, and
        ``timings["wall_time_s"]``.

    Raises
    ------
    hybridoc.errors.OptionError
        An unknown method or option (one line naming the valid ones).
    hybridoc.errors.SceneError
        A problem the method cannot handle (one line).
    hybridoc.errors.ConvergenceError
        The method found no solution at all.

    Examples
    --------
    >>> sol = hybridoc.solve("head-on", "gd", iters=50)  # doctest: +SKIP
    >>> sol.status, sol.cost  # doctest: +SKIP
    """
    from hybridoc.problem import as_ocp

    ocp = as_ocp(problem)
    m = get_method(method)
    missing = m.missing_features(ocp)
    reason = m.supports(ocp)
    if missing:
        reason = f"it does not honour {' or '.join(FEATURES[f] for f in missing)} yet"
    if reason:
        raise SceneError(f"method {method!r} cannot solve {ocp.name!r}: {reason}")
    names = m.option_names()
    bad = sorted(set(options) - set(names))
    if bad:
        takes = ", ".join(names) if names else "none"
        raise OptionError(
            f"method {method!r} takes no option(s) {', '.join(bad)}; it takes {takes}"
        )
    t0 = time.perf_counter()
    sol = m.function()(ocp, initial=initial, progress=progress, **options)
    sol.timings.setdefault("wall_time_s", time.perf_counter() - t0)
    _check_final_mode(ocp, sol)
    return sol


def _check_final_mode(ocp: HybridOCP, sol: Solution) -> None:
    """A successful Solution that ends outside the problem's required final mode is
    infeasible, whatever the method (its events are the judge's)."""
    if ocp.final_mode is None or not sol.success:
        return
    visited = sol.modes
    last = ocp.initial_mode if not visited else visited[-1]
    if last != ocp.final_mode:
        sol.set_status(
            "infeasible",
            f"the control ends in mode {last!r}, not in the required final mode "
            f"{ocp.final_mode!r} (judged)",
        )
