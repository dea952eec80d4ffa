"""Gradient descent as a registered method (:data:`METHOD`, ``method="gd"``): what it
supports, its summary lines and its crossval defaults and check."""

from __future__ import annotations

import math
from typing import Any

from hybridoc import tolerances
from hybridoc.methods import (
    Method,
    settings_lines,
)
from hybridoc.ocp import HybridOCP
from hybridoc.solution import Solution
from hybridoc.solvers.gd.options import GDOptions, checked_options
from hybridoc.solvers.gd.solve import solve_gd

GD_STARTS = {"disc": 32, "generic": 16}
"""Cross-validation runs gradient descent as a multi-start (``starts``), since a local method
from one guess can land in another basin (multiple-collision's two-event extremal); disc
scenes have aimed starts, hence more of them."""


GD_HOPS = 8
"""Hops (batched restarts, :func:`solve_gd`) of gradient descent in cross-validation on the
paper's symplectic Euler objective, whose kinks (a contact moving to another step) stall a
plain descent and are not taken past by :func:`past_kinks` (exact integrator only)."""


DISCRETE_TOLERANCE = tolerances.value("discrete")
"""Relative gap of gd's discrete loss to the optimum of its own discrete objective within
which the two agree in cross-validation
(:func:`~hybridoc.solvers.discrete_transcription.discrete_gap`)."""


def _supports(ocp: HybridOCP) -> str | None:
    """``None`` when gd can solve ``ocp``: its functions must be SX (the compiled step)."""
    for fn in (ocp.f, ocp.L, ocp.phi, ocp.terminal_eq, ocp.terminal_ineq):
        if fn is not None and not fn.is_a("SXFunction"):
            return f"the differentiable simulation needs SX functions; {fn.name()!r} is MX"
    return None


def _fmt(x: Any, digits: int) -> str:
    if x is None or math.isnan(float(x)):
        return "-"
    return f"{float(x):.{digits}g}"


def _summary_lines(sol: Solution) -> list[tuple[str, str]]:
    """What ``hybridoc solve`` prints about a gd solution: loss, iterations, settings."""
    lines = []
    if "loss" in sol.info:
        lines.append(("loss", f"{_fmt(sol.info['loss'], 12)} (the simulation's discrete loss)"))
    if "iterations" in sol.info:
        lines.append(("iterations", str(sol.info["iterations"])))
    if "horizon" in sol.info:
        lines.append(("final time", f"{_fmt(sol.info['horizon'], 12)} (free)"))
    if "terminal_violation" in sol.info:
        outer = len(sol.info.get("outer", []))
        lines.append((
            "constraints",
            f"terminal violation {_fmt(sol.info['terminal_violation'], 3)} (judged) after {outer} "
            "augmented-Lagrangian iteration(s)",
        ))  # fmt: skip
    return lines + settings_lines(sol)


def _crossval_defaults(ocp: HybridOCP, options: dict[str, Any]) -> dict[str, Any]:
    """Crossval's gd: a multi-start (:data:`GD_STARTS`), and :data:`GD_HOPS` hops on the
    symplectic Euler objective, whose kinks stall a descent, unless the caller sets them."""
    out = dict(options)
    if ocp.has_terminal_constraints or ocp.free_horizon:
        return out  # one augmented-Lagrangian run: the multi-start explores another loss
    aimed = ocp.capabilities.geometry is not None  # aimed starts (multistart.diverse_controls)
    out.setdefault("starts", GD_STARTS["disc" if aimed else "generic"])
    if out.get("integrator") == "symplectic-euler":
        out.setdefault("hops", GD_HOPS)
    return out


def _crossval_check(ocp: HybridOCP, sol: Solution) -> tuple[dict[str, Any], list[str]]:
    """On the symplectic Euler objective: gd's discrete loss against the optimum of that
    objective (:func:`~hybridoc.solvers.discrete_transcription.discrete_gap`), within
    :data:`DISCRETE_TOLERANCE`."""
    if sol.settings.get("integrator") != "symplectic-euler":
        return {}, []
    from hybridoc.solvers.discrete_transcription import discrete_gap

    entry = discrete_gap(ocp, sol)
    dgap = entry.get("discrete_gap_relative")
    reasons = []
    if dgap is not None and dgap > DISCRETE_TOLERANCE:
        reasons.append(
            f"gd's discrete loss is {dgap:+.3e} above the optimum of its own discrete "
            f"objective (the N-step transcription from its control), beyond "
            f"{DISCRETE_TOLERANCE:.0e}"
        )
    return entry, reasons


METHOD = Method(
    "gd",
    "gradient descent through the differentiable time-of-impact simulation",
    run=solve_gd,
    options=GDOptions,
    tolerance=tolerances.CROSSVAL,
    supports=_supports,
    summary_lines=_summary_lines,
    crossval_defaults=_crossval_defaults,
    crossval_check=_crossval_check,
    features=frozenset({"terminal", "free_horizon"}),
    check_options=checked_options,
)
"""Gradient descent as a registered method (``method="gd"``, :data:`hybridoc.methods.BUILTIN`);
it honours terminal constraints and a free final time (the augmented Lagrangian)."""
