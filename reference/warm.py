"""An extremal of a known sequence from a nearby problem's costates (warm start).

Datasets solve the reference for many draws of one scene: the nominal draw's event sequence
and shooting unknowns are a good start for every other draw. :func:`warm_extremal` solves
the sequence's HMP system by Newton from those unknowns, with continuation in the initial
state when Newton alone fails, verifies the extremal with the judge, and keeps it only when
cheap screens cannot show that another sequence does better; otherwise the caller runs the
full discovery (:func:`~hybridoc.reference.solve.solve_reference`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hybridoc import tolerances
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.reference.candidates import enumerate_sequences, lower_bound
from hybridoc.reference.result import ReferenceResult, make_result
from hybridoc.reference.sequence import COST_RTOL, judged_reference
from hybridoc.reference.shooting import newton, refine, shooting_system

__all__ = ["CONTINUATION", "SCREEN_RTOL", "warm_extremal"]

CONTINUATION: tuple[int, ...] = (4, 16)
"""Steps of the continuation in the initial state, tried in turn when Newton fails."""

SCREEN_RTOL = tolerances.CHEAPER
"""A screen rules out a rival only when it is cheaper by more than this, relative: the
table's ``"cheaper"`` tolerance (:mod:`hybridoc.tolerances`)."""


def _newton_with_continuation(
    ocp: HybridOCP,
    sequence: Sequence[str],
    z: np.ndarray,
    tol: float,
    start_x0: np.ndarray | None,
    continuation: Sequence[int],
):  # type: ignore[no-untyped-def]
    """Newton on the sequence's system from ``z``; if that fails and ``start_x0`` is given,
    continuation from the problem with that initial state, in each number of steps."""
    S = shooting_system(ocp, list(sequence))
    nr = newton(S, z, tol=tol)
    if nr.converged or start_x0 is None:
        return S, nr
    x_from, x_to = np.asarray(start_x0, dtype=float), np.asarray(ocp.x0, dtype=float)
    for steps in continuation:
        zk = z
        for k in range(1, steps + 1):
            Sk = shooting_system(ocp.replace(x0=x_from + (k / steps) * (x_to - x_from)), sequence)
            nr = newton(Sk, zk, tol=tol)
            if not nr.converged:
                break
            zk = nr.z
        if nr.converged:
            nr = newton(S, zk, tol=tol)
            if nr.converged:
                break
    return S, nr


def warm_extremal(
    ocp: HybridOCP,
    sequence: Sequence[str],
    z: np.ndarray,
    *,
    tol: float,
    start_x0: np.ndarray | None = None,
    continuation: Sequence[int] = CONTINUATION,
    rtol: float = COST_RTOL,
) -> tuple[ReferenceResult | None, str]:
    """The verified extremal of ``sequence`` from the shooting unknowns ``z``, or why not.

    Parameters
    ----------
    ocp
        The problem.
    sequence
        Its event sequence (guard names in order).
    z
        Shooting unknowns to start Newton from (a nearby problem's, e.g. ``res.z`` of the
        nominal draw's :class:`~hybridoc.reference.result.ReferenceResult`).
    tol
        Newton's tolerance on the HMP residual.
    start_x0
        The initial state of the problem ``z`` belongs to: when Newton fails, continuation
        in the initial state from it to ``ocp.x0``, in each number of ``continuation``
        steps.
    continuation
        The numbers of continuation steps to try, in turn.
    rtol
        The relative accuracy of the cost (as :func:`~hybridoc.reference.solve_reference`'s).

    Returns
    -------
    (result, why)
        ``result`` when Newton converged, the judge confirms the extremal, no sequence of at
        most one event other than ``sequence`` has a lower bound below its cost, the initial
        guess is not cheaper and the control bounds hold; else ``None`` and the reason.
    """
    S, nr = _newton_with_continuation(ocp, sequence, z, tol, start_x0, continuation)
    if not nr.converged:
        return None, f"Newton from the nominal point: residual {nr.residual:.2e}"
    ref = refine(S, nr, rtol=rtol, tol=tol)
    if not ref.ok:
        return None, ref.reason
    res, ok, _, msg = judged_reference(
        make_result(ref.system, ref.newton, "warm", ref.error), rtol=rtol, tol=tol
    )
    if not ok:
        return None, msg
    bound = res.cost * (1 - SCREEN_RTOL)
    for seq in enumerate_sequences(ocp, 1):
        if seq != list(sequence) and lower_bound(ocp, seq) < bound:
            return None, f"the sequence {seq} is not ruled out by its lower bound"
    if evaluate(ocp, ocp.u_guess).cost < bound:
        return None, "the initial guess is cheaper"
    if ocp.has_bounds and ocp.bound_violation(res.cell_averages()) > tolerances.FEASIBILITY:
        return None, "the extremal violates the control bounds"
    return res, ""
