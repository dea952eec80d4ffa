"""Exceptions raised for user errors.

Every problem a user can cause (a bad scene, a wrong array shape, NaN, a solver that did not
converge) raises a subclass of :class:`HybridocError` with one clear message. The CLI turns
these into one line on stderr and exit code 2.
"""

from __future__ import annotations


class HybridocError(Exception):
    """Base class of all user-facing errors in hybridoc."""


class SceneError(HybridocError, ValueError):
    """A scene file or scene object is invalid."""


class OptionError(SceneError):
    """An option of a method or a workflow is invalid: an unknown name, a wrong type or a
    value out of range. A :class:`ValueError`; a subclass of :class:`SceneError` for one
    release, so that code which caught the old error for a bad option keeps working."""


class ControlsError(HybridocError, ValueError):
    """A control array or controls file is invalid (shape, NaN, unreadable)."""


class EvaluationError(HybridocError, RuntimeError):
    """The event-exact evaluator cannot simulate this system faithfully.

    Raised for example for sustained contact or Zeno behaviour, which the impulsive model
    does not represent.
    """


class ConvergenceError(HybridocError, RuntimeError):
    """A solver did not converge to a point satisfying its optimality conditions."""


class SimultaneousEventError(EvaluationError):
    """Two guards fire at the same instant and their jumps do not commute.

    Attributes
    ----------
    guards
        The names of the two guards.
    time
        The event time.
    """

    def __init__(self, message: str, *, guards: tuple[str, str] = ("", ""), time: float = 0.0):
        super().__init__(message)
        self.guards = guards
        self.time = time
