"""Another simulator's gradient measured against the exact gradient of the continuous cost.

A gradient of the cost with respect to the piecewise-constant controls, computed by any other
means (MuJoCo's Jacobians chained backwards, finite differences over rollouts, a
differentiable simulator), is compared with the exact one, :func:`hybridoc.gradient` (the
adjoint with the hybrid minimum principle's jump relation), at the same controls.

Where the error lives
    Simulators that resolve contact on discrete steps are wrong mostly near events, so the
    grid cells are split by the judge's events (:attr:`hybridoc.Evaluation.events` of the same
    controls): the cells that end before the first event, the cells that hold an event
    (``t_n < gamma < t_{n+1}``), the cells between events, and the cells that start after the
    last event; a cell that touches an event only at its boundary counts as before or after
    it. Each part reports its own cosine and relative error and its share of the squared
    error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc.errors import HybridocError
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp

__all__ = [
    "GradientComparison",
    "GradientError",
    "GradientPart",
    "PHASES",
    "cell_phases",
    "compare_gradient",
    "gradient_figure",
]

#: The parts of the grid, in time order (see the module notes); a part without cells is left
#: out of :attr:`GradientComparison.phases`.
PHASES: tuple[str, ...] = (
    "before the first event",
    "cells with an event",
    "between events",
    "after the last event",
    "no events",
)


class GradientError(HybridocError, ValueError):
    """A given gradient cannot be compared: wrong shape, or NaN or infinite entries."""


@dataclass(frozen=True)
class GradientPart:
    """The given gradient against the exact one on some of its entries.

    Attributes
    ----------
    name
        Which entries: ``"all"``, a control label, or a part of the grid (:data:`PHASES`).
    cells
        The number of grid cells (rows) the entries come from.
    exact_norm, given_norm, error_norm
        2-norms of the exact gradient, the given one and their difference.
    cosine
        ``<g, g*> / (|g| |g*|)``; NaN when either is zero.
    relative_error
        ``|g - g*| / |g*|`` (infinite when ``g* = 0`` and ``g != g*``; 0 when both are 0).
    max_abs_error
        ``max |g - g*|`` over the entries.
    error_share
        This part's share of the squared error of the whole gradient (0 when that is 0).
    """

    name: str
    cells: int
    exact_norm: float
    given_norm: float
    error_norm: float
    cosine: float
    relative_error: float
    max_abs_error: float
    error_share: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields (NaN and infinity as ``None``)."""
        out: dict[str, Any] = {}
        for key, value in self.__dict__.items():
            out[key] = None if isinstance(value, float) and not math.isfinite(value) else value
        return out


@dataclass
class GradientComparison:
    """Result of :func:`compare_gradient`.

    Attributes
    ----------
    problem
        The problem's name.
    cost
        The judge's cost of the controls.
    overall
        All entries.
    components
        One part per control component (column), in the order of the control labels.
    phases
        One part per part of the grid that has cells (:data:`PHASES`, module notes).
    exact, given
        The ``(N, nu)`` gradients.
    controls
        The ``(N, nu)`` controls both gradients are taken at.
    time_grid
        The ``N + 1`` grid times.
    events
        The judge's events of the controls (JSON-ready dicts).
    cell_phase
        For each grid cell the index in :data:`PHASES` of its part.
    substeps
        ``K`` when the controls hold ``K`` values per interval of the problem's grid.
    """

    problem: str
    cost: float
    overall: GradientPart
    components: list[GradientPart]
    phases: list[GradientPart]
    exact: np.ndarray = field(repr=False)
    given: np.ndarray = field(repr=False)
    controls: np.ndarray = field(repr=False)
    time_grid: np.ndarray = field(repr=False)
    events: list[dict[str, Any]] = field(default_factory=list)
    cell_phase: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=int))
    substeps: int = 1

    @property
    def cosine(self) -> float:
        """The cosine between the whole gradients."""
        return self.overall.cosine

    @property
    def relative_error(self) -> float:
        """``|g - g*| / |g*|`` over the whole gradient."""
        return self.overall.relative_error

    @property
    def event_times(self) -> list[float]:
        """The judge's event times."""
        return [float(e["time"]) for e in self.events]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the parts, the events and the per-cell error norms."""
        return {
            "problem": self.problem,
            "cost": self.cost,
            "steps": int(self.exact.shape[0]),
            "substeps": self.substeps,
            "cosine": self.overall.to_dict()["cosine"],
            "relative_error": self.overall.to_dict()["relative_error"],
            "overall": self.overall.to_dict(),
            "components": [p.to_dict() for p in self.components],
            "phases": [p.to_dict() for p in self.phases],
            "events": list(self.events),
            "cell_phase": [PHASES[int(k)] for k in self.cell_phase],
            "cell_error_norm": np.linalg.norm(self.given - self.exact, axis=1).tolist(),
        }


def _part(name: str, cells: int, g: np.ndarray, e: np.ndarray, total_sq: float) -> GradientPart:
    # norms scaled by the largest entry: gradients near 1e300 have finite norms whose
    # squares are not
    def norm(x: np.ndarray) -> float:
        scale = float(np.max(np.abs(x), initial=0.0))
        return 0.0 if scale == 0.0 else scale * float(np.linalg.norm(x / scale))

    ne, ng, nd = norm(e), norm(g), norm(g - e)
    if ne > 0 and ng > 0:
        cos = float(np.sum((g / ng) * (e / ne)))
        cos = min(max(cos, -1.0), 1.0)
    else:
        cos = math.nan
    rel = nd / ne if ne > 0 else (0.0 if nd == 0 else math.inf)
    return GradientPart(
        name=name,
        cells=cells,
        exact_norm=ne,
        given_norm=ng,
        error_norm=nd,
        cosine=cos,
        relative_error=rel,
        max_abs_error=float(np.max(np.abs(g - e), initial=0.0)),
        error_share=(nd * nd / total_sq) if total_sq > 0 else 0.0,
    )


def cell_phases(time_grid: np.ndarray, event_times: list[float]) -> np.ndarray:
    """For each grid cell the index in :data:`PHASES` of its part (module notes).

    Parameters
    ----------
    time_grid
        The ``N + 1`` grid times.
    event_times
        The event times, in order.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` integers.
    """
    t = np.asarray(time_grid, dtype=float)
    n = t.size - 1
    if not event_times:
        return np.full(n, PHASES.index("no events"), dtype=int)
    ev = np.asarray(event_times, dtype=float)
    out = np.full(n, PHASES.index("between events"), dtype=int)
    mid = 0.5 * (t[:-1] + t[1:])
    out[mid < ev[0]] = PHASES.index("before the first event")
    out[mid > ev[-1]] = PHASES.index("after the last event")
    holds = np.any((t[:-1, None] < ev[None, :]) & (ev[None, :] < t[1:, None]), axis=1)
    out[holds] = PHASES.index("cells with an event")
    return out


def _given_array(given: Any, n: int, nu: int, flag: str) -> np.ndarray:
    from hybridoc.io import substeps_hint
    from hybridoc.ocp import as_float_array

    g = as_float_array(given, "the given gradient", error=GradientError)
    if g.ndim == 1 and g.size == n * nu:
        g = g.reshape(n, nu)
    if g.shape != (n, nu):
        hint = substeps_hint(g.shape[0], n, flag) if g.ndim == 2 and g.shape[1] == nu else ""
        raise GradientError(
            f"the given gradient has shape {g.shape}; expected ({n}, {nu}) (one row per grid "
            f"interval, one column per control) or {n * nu} values in that order{hint}"
        )
    if not np.all(np.isfinite(g)):
        row, col = np.argwhere(~np.isfinite(g))[0]
        raise GradientError(
            f"the given gradient has a non-finite value {g[row, col]} at row {row}, column {col}"
        )
    return g


def compare_gradient(
    problem: ProblemLike,
    given: Any,
    controls: ControlsLike | None = None,
    *,
    substeps: int = 1,
    flag: str = "substeps",
) -> GradientComparison:
    """Measure a gradient from elsewhere against the exact gradient at the same controls.

    Parameters
    ----------
    problem
        Any problem.
    given
        ``dJ/du`` from another simulator: ``(N, nu)``, or ``N * nu`` values in row order
        (``given[n * nu + j]`` for interval ``n`` and component ``j``).
    controls
        The ``(N, nu)`` controls the gradient was taken at (a Solution is accepted);
        default: the problem's initial guess.
    substeps
        ``K``: the controls and the gradient have ``K`` rows per interval of the problem's
        grid (a simulator that changes its control at each of ``K`` substeps); both are
        then taken on the ``K`` times finer grid (:func:`hybridoc.io.substep_problem`).
    flag
        How ``substeps`` is spelled in the error for a gradient of ``N * K`` rows
        (``"--substeps"`` on the command line).

    Returns
    -------
    GradientComparison

    Raises
    ------
    GradientError
        ``given`` has the wrong shape or non-finite entries.
    hybridoc.errors.EvaluationError
        The judge cannot simulate the controls (the exact gradient does not exist).
    """
    from hybridoc.evaluator import gradient
    from hybridoc.io import substep_problem

    ocp = substep_problem(as_ocp(problem), substeps)
    n, nu = ocp.steps, ocp.nu
    g = _given_array(given, n, nu, flag)
    exact = gradient(ocp, controls)
    e = np.asarray(exact.d_controls, dtype=float)
    u = np.asarray(exact.evaluation.controls, dtype=float)
    events = exact.evaluation.event_dicts()
    grid = np.asarray(ocp.time_grid(), dtype=float)
    phase = cell_phases(grid, [ev["time"] for ev in events])
    total_sq = _part("all", n, g, e, 0.0).error_norm ** 2
    overall = _part("all", n, g, e, total_sq)
    labels = list(ocp.control_labels or [])
    components = [_part(labels[j], n, g[:, j], e[:, j], total_sq) for j in range(nu)]
    phases = []
    for k, name in enumerate(PHASES):
        rows = phase == k
        if rows.any():
            phases.append(_part(name, int(rows.sum()), g[rows], e[rows], total_sq))
    return GradientComparison(
        problem=ocp.name,
        cost=float(exact.cost),
        overall=overall,
        components=components,
        phases=phases,
        exact=e,
        given=g,
        controls=u,
        time_grid=grid,
        events=events,
        cell_phase=phase,
        substeps=int(substeps),
    )


def gradient_figure(comparison: GradientComparison, *, label: str = "given") -> Any:
    """The two gradients against time, one panel per control component, and the error per
    cell, with the judge's event times marked.

    Parameters
    ----------
    comparison
        A :func:`compare_gradient` result.
    label
        The legend name of the given gradient.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    c = comparison
    nu = c.exact.shape[1]
    labels = [p.name for p in c.components]
    fig = Figure(figsize=(7.5, 2.0 * (nu + 1) + 0.6), layout="constrained")
    axes = fig.subplots(nu + 1, 1, sharex=True, squeeze=False)[:, 0]
    t = c.time_grid
    # per unit time: a gradient with respect to a cell's value scales with the cell's length,
    # so that gradients on grids of different N read on one scale
    width = np.diff(t)[:, None]
    for j, ax in enumerate(axes[:nu]):
        ax.stairs(
            c.exact[:, j] / width[:, 0],
            t,
            baseline=None,
            lw=1.4,
            color="k",
            label="exact (adjoint)",
        )
        ax.stairs(c.given[:, j] / width[:, 0], t, baseline=None, lw=1.0, color="C3", label=label)
        ax.set_ylabel(f"dJ/d {labels[j]}\nper unit time", fontsize=8)
    err = np.linalg.norm(c.given - c.exact, axis=1) / width[:, 0]
    axes[-1].stairs(err, t, baseline=None, lw=1.0, color="C0")
    axes[-1].set_ylabel("|error| per cell\nper unit time", fontsize=8)
    axes[-1].set_xlabel("time")
    for ax in axes:
        for k, te in enumerate(c.event_times):
            ax.axvline(te, color="0.4", ls="--", lw=0.8, label="judge's events" if k == 0 else None)
        ax.grid(True, lw=0.4, alpha=0.5)
    axes[0].legend(fontsize=7, loc="best")
    o = c.overall
    fig.suptitle(
        f"{c.problem}: {label} gradient against the exact one "
        f"(cosine {o.cosine:.4f}, relative error {o.relative_error:.3g})",
        fontsize=10,
    )
    return fig
