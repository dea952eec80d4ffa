"""Every solver behind one call: :func:`solve` and the :data:`METHODS` registry.

``hybridoc.solve(problem, method="reference" | "dt" | "gd", **options)`` runs a registered
method on any problem (a name, a ``.toml`` file, ``file.py:function``, a Scene or a
HybridOCP) and returns a :class:`~hybridoc.solution.Solution` with the uniform
``status``/``success``/``message``, the judge's ``cost`` and ``events``, and ``timings``.
Every method takes its initial guess as ``initial`` (controls or a Solution).

A new solver is one :func:`register_method` call: ``hybridoc solve --method``, ``crossval``
and the documentation read this registry. The contract of a method's ``run``: it takes the
problem as a :class:`~hybridoc.HybridOCP` and keyword options, raises
:class:`~hybridoc.errors.HybridocError` subclasses for user errors, and returns a Solution
whose cost is the judge's cost of its control and whose status says what the result is.
"""

from __future__ import annotations

import importlib
import inspect
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.solution import Solution

__all__ = ["METHODS", "Method", "crossval", "register_method", "solve"]


@dataclass(frozen=True)
class Method:
    """A registered solver.

    Attributes
    ----------
    name
        The ``method=`` value.
    summary
        One line for listings.
    run
        ``run(ocp, **options) -> Solution``, or ``"module:function"`` naming it (imported on
        first use, so that listing the methods imports no solver).
    supports
        ``supports(ocp) -> None`` when the method can solve the problem, else a one-line
        reason.
    """

    name: str
    summary: str
    run: Callable[..., Solution] | str
    supports: Callable[[HybridOCP], str | None] = field(default=lambda ocp: None)

    def function(self) -> Callable[..., Solution]:
        """The solver function."""
        if callable(self.run):
            return self.run
        module, _, attr = self.run.partition(":")
        return getattr(importlib.import_module(module), attr)

    def accepted(self) -> tuple[str, ...]:
        """The option names the solver accepts (read from its signature)."""
        params = inspect.signature(self.function()).parameters
        return tuple(
            p.name
            for p in params.values()
            if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
            and p.name not in ("ocp", "problem")
            and not p.name.startswith("_")
        )


METHODS: dict[str, Method] = {}
"""The registered methods, by name."""


def register_method(method: Method) -> Method:
    """Add a method to :data:`METHODS` (replacing one of the same name)."""
    METHODS[method.name] = method
    return method


def solve(
    problem: ProblemLike,
    method: str = "reference",
    *,
    initial: ControlsLike | None = None,
    **options: Any,
) -> Solution:
    """Solve a problem with a registered method.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`).
    method
        ``"reference"`` (HMP shooting), ``"dt"`` (direct transcription), ``"gd"`` (gradient
        descent through the differentiable simulation), or any method registered later.
    initial
        The initial guess: ``None`` (the problem's), ``(N, nu)`` controls or a Solution.
    **options
        The method's options (see ``hybridoc.solvers.registry.METHODS[method].accepted()``).

    Returns
    -------
    Solution
        With ``status``, ``success``, ``message``, the judge's ``cost`` and ``events``, and
        ``timings["wall_time_s"]``.

    Raises
    ------
    hybridoc.errors.SceneError
        An unknown method or option, or a problem the method cannot handle (one line).
    hybridoc.errors.ConvergenceError
        The method found no solution at all.
    """
    ocp = as_ocp(problem)
    m = METHODS.get(method)
    if m is None:
        raise SceneError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    reason = m.supports(ocp)
    if reason:
        raise SceneError(f"method {method!r} cannot solve {ocp.name!r}: {reason}")
    accepted = m.accepted()
    bad = sorted(set(options) - set(accepted))
    if bad:
        raise SceneError(
            f"method {method!r} takes no option(s) {', '.join(bad)}; it takes "
            f"{', '.join(o for o in accepted if o != 'initial')}"
        )
    t0 = time.perf_counter()
    sol = m.function()(ocp, initial=initial, **options)
    sol.timings.setdefault("wall_time_s", time.perf_counter() - t0)
    return sol


# ---------------------------------------------------------------------- built-in methods
def _reference_supports(ocp: HybridOCP) -> str | None:
    from hybridoc.reference import reference_supports

    return reference_supports(ocp)


def _gd_supports(ocp: HybridOCP) -> str | None:
    for fn in (ocp.f, ocp.L, ocp.phi):
        if not fn.is_a("SXFunction"):
            return f"the differentiable simulation needs SX functions; {fn.name()!r} is MX"
    return None


register_method(
    Method(
        "reference",
        "optimal control by shooting on the hybrid minimum principle (the ground truth)",
        "hybridoc.reference.solve:solve_reference",
        _reference_supports,
    )
)
register_method(
    Method(
        "dt",
        "multi-phase direct transcription (Radau collocation, IPOPT)",
        "hybridoc.solvers.transcription:solve_dt",
    )
)
register_method(
    Method(
        "gd",
        "gradient descent through the differentiable time-of-impact simulation",
        "hybridoc.solvers.gd:solve_gd",
        _gd_supports,
    )
)


def crossval(problem: ProblemLike, **options: Any) -> Any:
    """Cross-validate the registered methods on a problem; see
    :func:`hybridoc.solvers.validation.crossval`."""
    from hybridoc.solvers.validation import crossval as _crossval

    return _crossval(problem, **options)
