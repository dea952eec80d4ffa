"""The options of the transcription, :class:`DTOptions`, declared and checked once, and the
limits they are checked against.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import OptionError
from hybridoc.methods import option, positive_float

__all__ = [
    "DEFAULT_MESH",
    "DTOptions",
    "MAX_DEGREE",
    "MAX_ITER",
    "MAX_MESH",
    "TERMINAL_TOL",
    "checked_degree",
    "checked_mesh",
]


DEFAULT_MESH = 4


MAX_DEGREE = 9
"""The highest collocation degree: CasADi's Radau tables (``collocation_points``) stop at 9."""


MAX_MESH = 1000
"""The most collocation elements per phase (250 times the default): a typo such as
``--mesh 100000000`` fails with one line instead of building an NLP that fills the memory."""


MAX_ITER = 500  # IPOPT iterations per candidate NLP


TERMINAL_TOL = tolerances.TERMINAL  # the default judged terminal-constraint violation


def _is_int(x: Any) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


def checked_degree(degree: Any) -> int:
    """``degree`` as an int in ``[1, MAX_DEGREE]``, or an :class:`OptionError`."""
    if not _is_int(degree) or not 1 <= degree <= MAX_DEGREE:
        raise OptionError(
            f"degree must be an integer from 1 to {MAX_DEGREE} (the Radau collocation tables "
            f"go up to {MAX_DEGREE}), got {degree!r}"
        )
    return int(degree)


def checked_mesh(mesh: Any, phases: int | None) -> list[int]:
    """``mesh`` (None, one int or one per phase) as one int per phase; ``phases=None`` checks
    the values only (the number of phases depends on the candidate sequence)."""
    if mesh is None:
        mesh = DEFAULT_MESH
    values = [mesh] if _is_int(mesh) else mesh
    if isinstance(values, str) or not isinstance(values, Sequence | np.ndarray):
        raise OptionError(f"mesh must be an integer or a list of integers, got {mesh!r}")
    values = list(values)
    if not values or not all(_is_int(m) and 1 <= m <= MAX_MESH for m in values):
        raise OptionError(
            f"mesh must be elements per phase, integers from 1 to {MAX_MESH}, got {mesh!r}"
        )
    if _is_int(mesh):
        return [int(mesh)] * (phases or 1)
    if phases is not None and len(values) != phases:
        raise OptionError(f"mesh must be one integer or {phases} (one per phase), got {mesh!r}")
    return [int(m) for m in values]


def _checked_time_limit(time_limit: Any) -> None:
    """An :class:`OptionError` unless ``time_limit`` is ``None`` or a positive finite number."""
    if time_limit is not None and not (
        isinstance(time_limit, int | float)
        and not isinstance(time_limit, bool)
        and math.isfinite(time_limit)
        and time_limit > 0
    ):
        raise OptionError(f"time_limit must be a positive number of seconds, got {time_limit!r}")


def _checked_terminal_tol(terminal_tol: Any) -> None:
    """An :class:`OptionError` unless ``terminal_tol`` is a positive finite number."""
    if not (isinstance(terminal_tol, int | float) and 0 < terminal_tol < math.inf):
        raise OptionError(f"terminal_tol must be a positive number, got {terminal_tol!r}")


def _parse_bounded_int(text: str, what: str, most: int) -> int:
    """Command-line text as an integer from 1 to ``most`` (a ``ValueError`` naming ``what``)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= most:
        raise ValueError(f"{what} must be an integer from 1 to {most}, got {text!r}")
    return value


def _parse_mesh(text: str) -> int:
    return _parse_bounded_int(text, "mesh (collocation elements per phase)", MAX_MESH)


def _parse_degree(text: str) -> int:
    return _parse_bounded_int(text, "degree", MAX_DEGREE)


@dataclass(frozen=True)
class DTOptions:
    """The options of :func:`solve_dt` (``method="dt"``), declared once: their defaults are
    :func:`solve_dt`'s keywords' and ``hybridoc solve`` offers those with ``cli`` metadata as
    flags (``--sequence``, ``--mesh``, ``--degree``, ``--time-limit``, ``--terminal-tol``).

    Every value is checked when the options are made (:meth:`__post_init__`), the one place
    they are checked: an out-of-range ``degree``, ``mesh``, ``time_limit`` or
    ``terminal_tol`` is an :class:`~hybridoc.errors.OptionError`. What depends on the problem
    (``sequence``'s guard names, a ``mesh`` of one value per phase) is checked by
    :func:`run_dt` against the problem.
    """

    sequence: str | Sequence[str] | None = option(
        None,
        "comma-separated guard names in event order ('' for none)",
        metavar="EVENTS",
    )
    mesh: int | Sequence[int] | None = option(
        None,
        f"collocation elements per phase, at most {MAX_MESH} (default {DEFAULT_MESH})",
        parse=_parse_mesh,
    )
    degree: int = option(
        3, f"collocation degree, 1 to {MAX_DEGREE} (default 3)", parse=_parse_degree
    )
    time_limit: float | None = option(
        None,
        "stop after this much wall time and exit 2, returning the best candidate judged so "
        f"far (default: no limit; at most {MAX_ITER} IPOPT iterations per NLP)",
        parse=positive_float,
        metavar="SECONDS",
    )
    terminal_tol: float = option(
        TERMINAL_TOL,
        "the judged terminal-constraint violation above which a result is infeasible "
        f"(default {TERMINAL_TOL:g})",
        parse=positive_float,
        metavar="TOL",
    )
    verbose: bool = option(False, "print IPOPT's log and the candidates to stderr", cli=False)

    def __post_init__(self) -> None:
        """Check the options (:class:`~hybridoc.errors.OptionError`); ``degree`` becomes an
        ``int``."""
        object.__setattr__(self, "degree", checked_degree(self.degree))
        checked_mesh(self.mesh, None)
        _checked_time_limit(self.time_limit)
        _checked_terminal_tol(self.terminal_tol)
