"""Policy reports in words and figures (:mod:`hybridoc.workflows.policies`): which
constraints a policy's rollouts violate, and the figures of a
:class:`~hybridoc.workflows.policies.PolicyReport`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import tolerances

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.workflows.policies import PolicyReport

__all__ = [
    "policy_figures",
    "report_figures",
    "varying_coordinates",
    "violation_lines",
    "violation_phrases",
    "violation_summary",
    "violation_text",
]

# Evaluation.feasible's tolerances, per kind of violation (to say which ones a draw breaks)
_TOLERANCES = {
    "bound": tolerances.FEASIBILITY,
    "path": tolerances.FEASIBILITY,
    "terminal": tolerances.TERMINAL,
}
_VIOLATIONS = (
    ("bound", "control bounds"),
    ("path", "path constraints"),
    ("terminal", "terminal constraints"),
)


def violation_phrases(values: Any) -> list[str]:
    """What one judged control violates beyond the judge's tolerances, with how much.

    Parameters
    ----------
    values
        A mapping (or anything indexable by name) with ``bound_violation``,
        ``path_violation`` and ``terminal_violation`` (an
        :class:`~hybridoc.Evaluation`'s, e.g. in a report).

    Returns
    -------
    list of str
        E.g. ``["control bounds by 0.42", "terminal constraints by 1.7"]``; empty for a
        feasible control (the tolerances of :attr:`Evaluation.feasible
        <hybridoc.Evaluation>`).
    """
    return [
        f"{what} by {float(values[f'{key}_violation']):.3g}"
        for key, what in _VIOLATIONS
        if float(values[f"{key}_violation"]) > _TOLERANCES[key]
    ]


def violation_text(roll: dict[str, np.ndarray]) -> np.ndarray:
    """Per draw, what its controls violate and by how much (empty where nothing does)."""
    out = []
    for k in range(roll["feasible"].size):
        parts = violation_phrases({f"{key}_violation": roll[f"{key}_violation"][k]
                                   for key, _ in _VIOLATIONS})  # fmt: skip
        out.append("the policy's controls violate the " + ", ".join(parts) if parts else "")
    return np.array(out, dtype=str)


def violation_summary(columns: dict[str, np.ndarray]) -> dict[str, Any]:
    """What the infeasible rollouts among some judged ones violate, per kind.

    Parameters
    ----------
    columns
        Per rollout: ``bound_violation``, ``path_violation``, ``terminal_violation`` (the
        judge's; NaN for a rollout the judge could not simulate) and ``feasible``
        (:attr:`Evaluation.feasible <hybridoc.Evaluation>`).

    Returns
    -------
    dict
        Per kind ``bound``, ``path``, ``terminal``: ``draws`` (infeasible rollouts that
        violate it beyond the judge's tolerance) and ``max`` (the largest violation over
        the judged rollouts; ``None`` when none was judged).
    """
    judged = ~np.isnan(np.asarray(columns["bound_violation"], dtype=float))
    infeasible = judged & ~np.asarray(columns["feasible"], dtype=bool)
    out: dict[str, Any] = {}
    for key, _ in _VIOLATIONS:
        v = np.asarray(columns[f"{key}_violation"], dtype=float)
        out[key] = {
            "draws": int(np.sum(infeasible & (v > _TOLERANCES[key]))),
            "max": float(np.max(v[judged])) if judged.any() else None,
        }
    return out


def violation_lines(violations: dict[str, Any]) -> list[str]:
    """What infeasible draws violate, one phrase per kind of constraint.

    Parameters
    ----------
    violations
        :func:`violation_summary` (``PolicyReport.summary["violations"]``).

    Returns
    -------
    list of str
        E.g. ``"control bounds on 3 draw(s) (by up to 0.42)"``; empty when no draw
        violates anything.
    """
    lines = []
    for key, what in _VIOLATIONS:
        v = violations[key]
        if v["draws"]:
            lines.append(f"{what} on {v['draws']} draw(s) (by up to {v['max']:.3g})")
    return lines


def varying_coordinates(x0: np.ndarray, labels: list[str]) -> list[tuple[int, str]]:
    """The (index, label) of the state components that vary across draws, widest first."""
    spread = np.ptp(x0, axis=0) if x0.size else np.zeros(len(labels))
    order = np.argsort(-spread, kind="stable")
    return [(int(i), labels[i]) for i in order if spread[i] > 0]


def policy_figures(report: PolicyReport, labels: list[str], title: str) -> dict[str, Any]:
    """The gap histogram and the gap over the initial-state space of a report.

    Parameters
    ----------
    report
        A :class:`PolicyReport`.
    labels
        The state labels (``HybridOCP.state_labels``), naming the scatter plot's axes.
    title
        The start of each figure's title.

    Returns
    -------
    dict
        ``{"gap_hist": Figure, "gap_scatter": Figure}``: matplotlib figures made without
        pyplot, so no backend is chosen or changed.
    """
    from matplotlib.figure import Figure

    c = report.columns
    ok = np.isfinite(c["gap"])
    fig = Figure(figsize=(6.4, 4.2), layout="tight")
    ax = fig.add_subplot()
    rel = c["rel_gap"][ok]
    if rel.size:
        ax.hist(100 * rel, bins=min(50, max(10, rel.size // 10)), color="tab:blue", alpha=0.8)
        med = float(np.median(rel))
        ax.axvline(100 * med, color="k", ls="--", lw=1, label=f"median {100 * med:.3g}%")
        ax.legend()
    ax.set_xlabel("relative cost gap to the reference [%]")
    ax.set_ylabel("draws")
    n_bad = int(np.sum(c["status"] == "infeasible"))
    # the feasible draws only: an infeasible policy's gap is not its gap
    extra = f" ({n_bad} with the policy infeasible: not compared)" if n_bad else ""
    ax.set_title(f"{title}: gap over {int(ok.sum())} draws{extra}", fontsize=10)
    hist = fig

    fig = Figure(figsize=(6.4, 5.2), layout="tight")
    ax = fig.add_subplot()
    coords = varying_coordinates(c["x0"], labels)
    if coords:
        i = coords[0][0]
        j = coords[1][0] if len(coords) > 1 else None
        x = c["x0"][:, i]
        y = c["x0"][:, j] if j is not None else c["gap"]
        sc = ax.scatter(
            x[ok], y[ok], c=100 * c["rel_gap"][ok], cmap="viridis", s=14, label="draw (colour: gap)"
        )
        fig.colorbar(sc, ax=ax, label="relative gap [%]")
        mm = ok & c["mismatch"]
        if mm.any():
            ax.scatter(x[mm], y[mm], marker="x", c="red", s=36, lw=1.2,
                       label=f"events differ from the optimum ({int(mm.sum())})")  # fmt: skip
        infeasible = c["status"] == "infeasible"
        if infeasible.any():
            ax.scatter(x[infeasible], np.nan_to_num(y[infeasible]), marker="^", c="tab:red",
                       s=30, label=f"policy infeasible ({int(infeasible.sum())})")  # fmt: skip
        bad = ~ok & ~infeasible
        if bad.any():
            ax.scatter(x[bad], np.nan_to_num(y[bad]), marker="s", facecolors="none",
                       edgecolors="k", s=30, label=f"not compared ({int(bad.sum())})")  # fmt: skip
        ax.set_xlabel(f"initial {labels[i]}")
        ax.set_ylabel(f"initial {labels[j]}" if j is not None else "gap")
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3,
                  frameon=False)  # fmt: skip
    else:
        ax.text(0.5, 0.5, "the initial state does not vary", ha="center", transform=ax.transAxes)
    ax.set_title(f"{title}: gap over the initial states", fontsize=10)
    return {"gap_hist": hist, "gap_scatter": fig}


def report_figures(report: PolicyReport, labels: list[str], stem: Path, title: str) -> list[Path]:
    """:func:`policy_figures` written as ``<stem>_gap_hist.png`` and ``<stem>_gap_scatter.png``."""
    from hybridoc.plotting import save_figure

    figs = policy_figures(report, labels, title)
    return [save_figure(fig, f"{stem}_{name}.png") for name, fig in figs.items()]
