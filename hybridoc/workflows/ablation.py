"""The paper's Table 1 rerun: plain gradient descent with each time-of-impact setting.

``hybridoc ablation`` prints what :func:`run_ablation` returns beside the paper's numbers
(:mod:`hybridoc.problems.paper`, where each is stated once).

Plain gradient descent at the paper's learning rates does not settle in every cell: with
TOI-Velocity alone on single-collision it bounces across a kink of the loss to its last
iteration (between 0.480 and 0.499 over the last :data:`LAST_WINDOW` iterations), so its
final loss is one draw from that range and the last bit of the update moves it. The
paper's ``torch.optim.SGD`` adds ``-lr * g`` with one rounding (a fused multiply-add):
0.48058; numpy's ``x - lr * g`` (two roundings, since commit 0b1d90b) gives 0.49471, and
learning rates within two ulps of the paper's give 0.481 to 0.504 with either. Each row
carries that range (``loss_last_min``, ``loss_last_max``) beside the final loss.
"""

from __future__ import annotations

from typing import Any

from hybridoc.problems.paper import PAPER_OPTIMUM, PAPER_SETTINGS, PAPER_TABLE1
from hybridoc.progress import ProgressLike

__all__ = ["LAST_WINDOW", "ablation_cell", "run_ablation"]

LAST_WINDOW = 50
"""The last iterations over which each row reports the range of the loss: a cell whose
range is wide did not settle, and its final loss is one draw from that range."""


def ablation_cell(name: str, toi: str, progress: ProgressLike = False) -> Any:
    """One cell of Table 1: plain gd on the paper problem ``name`` with time-of-impact
    setting ``toi``, the paper's symplectic Euler, learning rate and iterations
    (:data:`~hybridoc.problems.paper.PAPER_SETTINGS`); the Solution."""
    from hybridoc.solvers.gd import solve_gd

    lr, iters = PAPER_SETTINGS[name]
    return solve_gd(
        name, toi=toi, integrator="symplectic-euler", optimizer="gd", lr=lr, iters=iters,
        progress=progress,
    )  # fmt: skip


def run_ablation(progress: ProgressLike = False) -> dict[str, Any]:
    """Plain gd with each TOI setting on both paper problems (the paper's Table 1).

    Each run is :func:`hybridoc.solvers.gd.solve_gd` with the paper's symplectic Euler,
    direct impulses, plain gradient descent and the paper's learning rate and iteration
    count (:data:`~hybridoc.problems.paper.PAPER_SETTINGS`).

    Parameters
    ----------
    progress
        ``False``/``None`` (silent), ``True`` (a meter on stderr) or a
        :class:`~hybridoc.progress.Progress`, passed to each run.

    Returns
    -------
    dict
        ``"rows"``: one dict per problem and TOI setting, in the order of
        ``PAPER_SETTINGS`` and :data:`~hybridoc.solvers.contacts.TOI_MODES`, with ``scene``,
        ``toi``, ``loss`` (the final discrete loss), ``loss_last_min`` and
        ``loss_last_max`` (its range over the last :data:`LAST_WINDOW` iterations), ``cost``
        (the judge's cost of the learned controls), ``paper_loss``, ``paper_optimum``,
        ``lr``, ``iterations``, ``events`` and ``loss_history``; ``"solutions"``:
        ``{(toi, scene): Solution}``.

    Examples
    --------
    >>> rows = run_ablation()["rows"]  # doctest: +SKIP
    >>> [(r["toi"], round(r["loss"], 4)) for r in rows[:2]]  # doctest: +SKIP
    """
    import numpy as np

    from hybridoc.solvers.contacts import TOI_MODES

    rows, sols = [], {}
    for name, (lr, _) in PAPER_SETTINGS.items():
        for toi in TOI_MODES:
            sol = ablation_cell(name, toi, progress)
            sols[(toi, name)] = sol
            last = np.asarray(sol.arrays["loss_history"], dtype=float)[-LAST_WINDOW:]
            rows.append(
                {
                    "scene": name,
                    "toi": toi,
                    "loss": sol.info["loss"],
                    "loss_last_min": float(last.min()),
                    "loss_last_max": float(last.max()),
                    "cost": sol.cost,
                    "paper_loss": PAPER_TABLE1[toi][name],
                    "paper_optimum": PAPER_OPTIMUM[name],
                    "lr": lr,
                    "iterations": sol.info["iterations"],
                    "events": sol.events,
                    "loss_history": sol.arrays["loss_history"],
                }
            )
    return {"rows": rows, "solutions": sols}
