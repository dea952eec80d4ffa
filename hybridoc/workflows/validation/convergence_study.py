"""Convergence in N (:func:`convergence`): each method's cost on grids of N cells against
the reference, by what its control can express (a method continuous in time averaged on
each grid, a method on the grid re-run at each N), with the observed orders, and its
log-log figure."""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import OptionError
from hybridoc.methods import BUILTIN, METHODS, REFERENCE_METHOD, solve
from hybridoc.problem import ProblemLike, as_ocp

if TYPE_CHECKING:  # pragma: no cover
    pass

__all__ = [
    "DEFAULT_STEPS",
    "convergence",
    "convergence_figure",
    "observed_orders",
]


#: Grid sizes of the convergence study.
DEFAULT_STEPS: tuple[int, ...] = (60, 120, 240, 480, 960)


def observed_orders(steps: Sequence[int], errors: Sequence[float]) -> list[float | None]:
    """Observed orders ``log(e_k / e_{k+1}) / log(N_{k+1} / N_k)``, ``None`` at the first N."""
    out: list[float | None] = [None]
    for k in range(1, len(steps)):
        a, b = errors[k - 1], errors[k]
        if a > 0 and b > 0 and math.isfinite(a) and math.isfinite(b):
            out.append(math.log(a / b) / math.log(steps[k] / steps[k - 1]))
        else:
            out.append(None)
    return out


def convergence(
    problem: ProblemLike,
    *,
    steps: Sequence[int] = DEFAULT_STEPS,
    methods: Sequence[str] | None = None,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    gd_options: dict[str, Any] | None = None,
    include_gd: bool = True,
) -> dict[str, Any]:
    """Costs of methods on grids of N cells, against the reference.

    What a method's cost at N is depends on what its control can express
    (:attr:`~hybridoc.methods.Method.representation`). A ``"continuous"`` method (the
    direct transcription) is solved once, from the reference; its optimum is a
    continuous-time control (exact for disc scenes, independent of N), and its
    N-dependent cost is that of its cell averages on the N-grid, judged piecewise constant
    by the evaluator: what a user of an N-step simulator gets from it. A ``"grid"`` method
    (gradient descent) is re-run at each N; its cost is the true continuous cost of its
    piecewise-constant control.

    Parameters
    ----------
    problem
        Any problem.
    steps
        The grid sizes N.
    methods
        Registered method names; default: every built-in method but the reference.
    options
        ``{method: {option: value}}`` passed to :func:`hybridoc.solve`.
    gd_options, include_gd
        Deprecated: ``options={"gd": ...}`` and ``methods`` without ``"gd"``.

    Returns
    -------
    dict
        ``problem``, ``steps``, ``methods``, ``reference_cost``,
        ``<method>_continuous_cost`` for each continuous method, and for each method a block
        with lists ``cost``, ``error`` (``|J_N - J*| / J*``) and ``order`` (observed,
        against N); a grid method's block also has ``discrete_loss`` (its
        ``info["loss"]``) and ``solve_time_s`` at each N.
    """
    from hybridoc.ocp import MAX_STEPS

    ocp = as_ocp(problem)
    steps = tuple(steps)
    if not steps or not all(
        isinstance(n, numbers.Integral) and not isinstance(n, bool) and 1 <= n <= MAX_STEPS
        for n in steps
    ):
        raise OptionError(
            f"steps must be a non-empty list of integers from 1 to {MAX_STEPS}, got {steps!r}"
        )
    names, opts = _convergence_methods(methods, options, gd_options, include_gd)
    ref = solve(ocp, REFERENCE_METHOD)
    out: dict[str, Any] = {
        "problem": ocp.name,
        "steps": [int(n) for n in steps],
        "methods": names,
        "reference_cost": float(ref.cost),
    }
    continuous = {}
    for name in names:
        if METHODS[name].representation == "continuous":
            continuous[name] = solve(ocp, name, initial=ref, **opts[name])
            out[f"{name}_continuous_cost"] = float(continuous[name].cost)
    costs: dict[str, list[float]] = {name: [] for name in names}
    losses: dict[str, list[float]] = {name: [] for name in names if name not in continuous}
    times: dict[str, list[float]] = {name: [] for name in losses}
    for n in steps:
        sc = ocp.replace(steps=int(n))
        for name in names:
            if name in continuous:  # its control's cell averages on the N-grid, judged
                costs[name].append(float(continuous[name].to_grid(problem=sc).cost))
                continue
            t0 = time.perf_counter()
            g = solve(sc, name, **opts[name])
            times[name].append(time.perf_counter() - t0)
            costs[name].append(float(g.cost))
            losses[name].append(float(g.info.get("loss", float("nan"))))
    J = ref.cost
    for name in names:
        err = [abs(c - J) / J for c in costs[name]]
        out[name] = {"cost": costs[name], "error": err, "order": observed_orders(steps, err)}
        if name in losses:
            out[name]["discrete_loss"] = losses[name]
            out[name]["solve_time_s"] = times[name]
    return out


def _convergence_methods(
    methods: Sequence[str] | None,
    options: Mapping[str, Mapping[str, Any]] | None,
    gd_options: dict[str, Any] | None,
    include_gd: bool,
) -> tuple[list[str], dict[str, dict[str, Any]]]:
    """The methods of a convergence study and their options, with the deprecated
    ``gd_options`` and ``include_gd`` (which named one method) mapped onto them."""
    import warnings

    given = [m for m in BUILTIN if m != REFERENCE_METHOD] if methods is None else list(methods)
    opts = {k: dict(v) for k, v in (options or {}).items()}
    if gd_options is not None or not include_gd:
        warnings.warn(
            "convergence(gd_options=, include_gd=) is deprecated: use options={'gd': ...} and "
            "methods=[...]",
            DeprecationWarning,
            stacklevel=3,
        )
        if gd_options is not None:
            opts["gd"] = {**gd_options, **opts.get("gd", {})}
        if not include_gd:
            given = [m for m in given if m != "gd"]
    names = list(dict.fromkeys(m for m in given if m != REFERENCE_METHOD))
    unknown = [m for m in [*names, *opts] if m not in METHODS]
    if unknown or not names:
        raise OptionError(
            f"convergence needs registered methods other than the reference; got "
            f"{unknown or names}, choose from {', '.join(METHODS)}"
        )
    return names, {name: opts.get(name, {}) for name in names}


def convergence_figure(report: dict[str, Any]) -> Any:
    """Log-log plot of the relative cost errors against N."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.4), layout="constrained")
    ax = fig.subplots()
    steps = np.array(report["steps"], dtype=float)
    names = _report_methods(report)
    for k, name in enumerate(names):
        err = np.array(report[name]["error"], dtype=float)
        ok = err > 0
        label = (
            f"{name}, cell averages on the N-grid"
            if f"{name}_continuous_cost" in report
            else f"{name} at N (true continuous cost)"
        )
        ax.loglog(steps[ok], err[ok], marker="osD^v<>"[k % 7], label=label)
    first = report[names[0]]["error"][0] if names else 0.0
    e0 = first if first > 0 else 1e-6
    ax.loglog(steps, e0 * steps[0] / steps, "k--", lw=0.8, label="slope -1")
    ax.loglog(steps, e0 * steps[0] ** 2 / steps**2, "k:", lw=1, label="slope -2")
    ax.set_xlabel("N (grid cells)")
    ax.set_ylabel("|J_N - J*| / J*")
    ax.set_title(f"{report['problem']}: convergence to the reference optimum")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


def _report_methods(report: Mapping[str, Any]) -> list[str]:
    """The methods of a convergence report (its ``methods``; a report written before it
    had them: its blocks)."""
    if "methods" in report:
        return list(report["methods"])
    return [k for k, v in report.items() if isinstance(v, Mapping) and "error" in v]
