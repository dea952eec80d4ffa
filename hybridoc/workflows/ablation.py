"""The paper's Table 1 rerun: plain gradient descent with each time-of-impact setting.

``hybridoc ablation`` prints what :func:`run_ablation` returns beside the paper's numbers
(:mod:`hybridoc.problems.paper`, where each is stated once).
"""

from __future__ import annotations

from typing import Any

from hybridoc.problems.paper import PAPER_OPTIMUM, PAPER_SETTINGS, PAPER_TABLE1
from hybridoc.progress import ProgressLike

__all__ = ["run_ablation"]


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
        ``toi``, ``loss`` (the final discrete loss), ``cost`` (the judge's cost of the
        learned controls), ``paper_loss``, ``paper_optimum``, ``lr``, ``iterations``,
        ``events`` and ``loss_history``; ``"solutions"``: ``{(toi, scene): Solution}``.

    Examples
    --------
    >>> rows = run_ablation()["rows"]  # doctest: +SKIP
    >>> [(r["toi"], round(r["loss"], 4)) for r in rows[:2]]  # doctest: +SKIP
    """
    from hybridoc.solvers.contacts import TOI_MODES
    from hybridoc.solvers.gd import solve_gd

    rows, sols = [], {}
    for name, (lr, iters) in PAPER_SETTINGS.items():
        for toi in TOI_MODES:
            sol = solve_gd(
                name, toi=toi, integrator="symplectic-euler", optimizer="gd", lr=lr, iters=iters,
                progress=progress,
            )  # fmt: skip
            sols[(toi, name)] = sol
            rows.append(
                {
                    "scene": name,
                    "toi": toi,
                    "loss": sol.info["loss"],
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
