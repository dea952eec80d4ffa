"""The options of the reference (method ``"reference"``), each declared once.

:class:`ReferenceOptions` is the one place where an option of :func:`~hybridoc.reference.
solve_reference` is declared: its default, its help (``hybridoc reference`` and
``hybridoc solve --method reference`` build their flags from it, :func:`hybridoc.methods.
option_specs`) and its check (:meth:`ReferenceOptions.__post_init__`, a
:class:`~hybridoc.errors.OptionError` for a bad value). ``solve_reference(problem, **kw)``
builds the options from its keywords (:meth:`ReferenceOptions.of`); its keyword signature is
generated from the dataclass (:func:`option_keywords`), so the defaults are not written
twice.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from hybridoc.errors import OptionError
from hybridoc.methods import option, options_signature, positive_float
from hybridoc.reference.sequence import COST_RTOL, RTOL_RANGE, check_rtol
from hybridoc.reference.sources import CandidateSource, SequenceStarter

__all__ = [
    "DEFAULT_BUDGET",
    "MAX_EVENTS",
    "MAX_SEARCH",
    "MULTISTART",
    "ReferenceOptions",
    "option_keywords",
    "parse_budget",
    "parse_search",
]

MAX_SEARCH = 8
"""The longest sequences ``search`` may enumerate. Their number grows about sevenfold per
event on two- and three-disc scenes (multiple-collision: 151 sequences of up to 5 events,
3 048 of up to 8, 169 668 of up to 12), each a Newton solve: beyond 8 a search runs for hours
and its lists fill the memory."""
MAX_EVENTS = 40
"""The longest event sequence the reference solves. Its disc NLP (event times and phase
controls, in single shooting) has dense derivatives: measured on 2 cores, one sequence of
32 events took 3 s and 0.3 GB, 63 events 22 s and 1.4 GB, 126 events 220 s and 8.8 GB
(time ~ K^3, memory ~ K^2.7), and a whole run tries the guess's sequence, its neighbours and
the transcription (39 events: 63 s in all). Longer sequences are not attempted (a given one
is refused); ``hybridoc evaluate``, ``solve --method gd`` or ``--method dt`` handle long
horizons."""
MULTISTART = 8
"""Starts of the batched multi-start source that proposes sequences (0 to skip it)."""
DEFAULT_BUDGET = 30.0
"""Seconds the default reference (without ``sequence``) may spend: its sources get what is
left of it, and the enumeration stops when it is spent (``budget``)."""


def _search_error(value: object) -> str | None:
    """Why ``value`` is not a ``search`` (an integer from 0 to :data:`MAX_SEARCH`), or
    ``None``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
        return f"search must be an integer >= 0, got {value!r}"
    if value > MAX_SEARCH:
        return (
            f"search must be at most {MAX_SEARCH} events (the number of sequences grows "
            f"about sevenfold per event), got {value}"
        )
    return None


def _seconds_error(name: str, value: object) -> str | None:
    """Why ``value`` is not a number of seconds > 0 (``budget``, ``time_limit``), or
    ``None``."""
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Real)
        or not (math.isfinite(value) and value > 0)
    ):
        return f"{name} must be a number of seconds > 0, got {value!r}"
    return None


def parse_search(text: str) -> int:
    """The ``--search K`` value: an integer from 0 to :data:`MAX_SEARCH`.

    Raises
    ------
    ValueError
        With a one-line reason.
    """
    try:
        k = int(text)
    except ValueError:
        raise ValueError(f"search must be an integer >= 0, got {text!r}") from None
    if k < 0:
        raise ValueError(f"search must be an integer >= 0, got {text!r}")
    why = _search_error(k)
    if why:
        raise ValueError(why)
    return k


def parse_budget(text: str) -> float:
    """The ``--budget SECONDS`` value: a positive number of seconds.

    Raises
    ------
    ValueError
        With a one-line reason.
    """
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"budget must be a number of seconds > 0, got {text!r}") from None
    if _seconds_error("budget", value):
        raise ValueError(f"budget must be a number of seconds > 0, got {text!r}")
    return value


def _sources_error(sources: object) -> str | None:
    """Why ``sources`` is not ``None`` or a list of candidate sources, or ``None``."""
    if sources is None:
        return None
    if isinstance(sources, str) or not isinstance(sources, Sequence):
        return f"sources must be a list of candidate sources, got {sources!r}"
    for s in sources:
        if not isinstance(s, CandidateSource | SequenceStarter):
            return (
                "a candidate source needs a name and a propose(ocp, context) or "
                f"start(ocp, sequence, guess, controls) method, got {type(s).__name__}"
            )
    return None


@dataclass(frozen=True)
class ReferenceOptions:
    """The options of :func:`~hybridoc.reference.solve_reference` (method ``"reference"``).

    Each field is declared here once, with its default, its help (the command-line flags
    are built from it) and its check: :meth:`__post_init__` raises
    :class:`~hybridoc.errors.OptionError` for a bad value. What depends on the problem (a
    ``sequence``'s guard names, its length against :data:`MAX_EVENTS`) is checked by the
    solve.
    """

    sequence: str | Sequence[str] | None = option(
        None,
        "comma-separated guard names in event order, e.g. 'ball1|ball2,ball2|wall' (an "
        "empty string: no event); default: search for the optimum",
        metavar="EVENTS",
    )
    search: int | None = option(
        None,
        "also enumerate every feasible event sequence of up to K events and report the "
        f"landscape of extremals (K at most {MAX_SEARCH})",
        parse=parse_search,
        metavar="K",
    )
    budget: float = option(
        DEFAULT_BUDGET,
        "seconds the search for the optimum may take (the sources get what is left; the "
        "enumeration of sequences stops when it is spent, and the coverage says so); "
        f"default {DEFAULT_BUDGET:g}",
        parse=parse_budget,
        metavar="SECONDS",
    )
    time_limit: float | None = option(
        None,
        "a hard wall-clock limit over the whole solve, sources included (checked between "
        "stages and sequences): the best verified extremal found by then is returned as "
        "not-converged; default none (the budget stays the search's soft limit)",
        parse=positive_float,
        metavar="SECONDS",
    )
    verbose: bool = option(
        False,
        "print Newton's iterations, the integration's refinements and the candidates to stderr",
    )
    rtol: float = option(
        COST_RTOL,
        "relative accuracy of the cost: the integration of generic problems is refined until "
        "its error estimate is within it, and the judge's re-simulation must agree to it "
        f"(from {RTOL_RANGE[0]:g} to {RTOL_RANGE[1]:g}); default {COST_RTOL:g}",
        parse=check_rtol,
        metavar="RTOL",
    )
    tol: float = option(1e-10, "max-norm of the HMP residual required", cli=False)
    verify: bool = option(
        True, "re-simulate the result with the judge (only a given sequence may skip it)",
        cli=False,
    )  # fmt: skip
    transcription: bool = option(
        True, "use the candidate source 'transcription' (proposals and warm starts)", cli=False
    )
    multistart: int = option(
        MULTISTART, "starts of the candidate source 'multi-start' (0 to skip it)", cli=False
    )
    sources: Sequence[Any] | None = option(
        None,
        "candidate sources (hybridoc.reference.sources); default: the registered ones",
        cli=False,
    )

    def __post_init__(self) -> None:
        """Check every option (the one place): an :class:`~hybridoc.errors.OptionError`
        naming the first bad one. ``rtol``, ``budget`` and ``time_limit`` are kept as
        floats."""
        tol = self.tol
        if not (isinstance(tol, numbers.Real) and math.isfinite(tol) and tol > 0):
            raise OptionError(f"tol must be a positive finite number, got {tol!r}")
        if self.search is not None:
            why = _search_error(self.search)
            if why:
                raise OptionError(why)
        try:
            rtol = check_rtol(self.rtol)
        except ValueError as exc:
            raise OptionError(str(exc)) from None
        why = _seconds_error("budget", self.budget)
        if why is None and self.time_limit is not None:
            why = _seconds_error("time_limit", self.time_limit)
        why = why or _sources_error(self.sources)
        if why:
            raise OptionError(why)
        m = self.multistart
        if isinstance(m, bool) or not isinstance(m, numbers.Integral) or m < 0:
            # int(2.5) in the search would hide a mistake; -1 failed deep inside gd
            raise OptionError(f"multistart must be an integer >= 0, got {m!r}")
        object.__setattr__(self, "rtol", rtol)
        object.__setattr__(self, "budget", float(self.budget))
        object.__setattr__(self, "multistart", int(self.multistart))
        if self.time_limit is not None:
            object.__setattr__(self, "time_limit", float(self.time_limit))

    @classmethod
    def of(
        cls,
        options: ReferenceOptions | None = None,
        overrides: Mapping[str, Any] | None = None,
        *,
        caller: str = "solve_reference",
    ) -> ReferenceOptions:
        """``options`` (default: the defaults) with the fields named in ``overrides``
        replaced, checked.

        Raises
        ------
        TypeError
            An override that is not an option (as Python says of an unknown keyword of
            ``caller``).
        hybridoc.errors.OptionError
            ``options`` is not a :class:`ReferenceOptions`, or a bad value.
        """
        if options is not None and not isinstance(options, cls):
            raise OptionError(
                f"{caller}'s options must be a ReferenceOptions, got {type(options).__name__}"
            )
        overrides = dict(overrides or {})
        names = {f.name for f in dataclasses.fields(cls)}
        for name in overrides:
            if name not in names:
                raise TypeError(f"{caller}() got an unexpected keyword argument {name!r}")
        if options is None:
            return cls(**overrides)
        return dataclasses.replace(options, **overrides) if overrides else options


_F = TypeVar("_F", bound=Callable[..., Any])


def option_keywords(options: type) -> Callable[[_F], _F]:
    """A decorator: the signature of ``fn(problem, options=None, /, *, <keywords>,
    **overrides)`` as :func:`inspect.signature` shows it (help, Sphinx, the conformance test
    :meth:`hybridoc.methods.Method.check_signature`) lists every field of the ``options``
    dataclass as a keyword with its default, read from the dataclass: the defaults are
    declared there only."""

    def decorate(fn: _F) -> _F:
        sig = options_signature(fn, options)
        fn.__signature__ = sig.replace(  # type: ignore[attr-defined]
            parameters=[
                p if p.kind is p.KEYWORD_ONLY else p.replace(kind=p.POSITIONAL_ONLY)
                for p in sig.parameters.values()
            ]
        )
        return fn

    return decorate
