"""What a result may claim: the candidate chosen, its status and message, and a cheaper
control that is known.
"""

from __future__ import annotations

from typing import Any

from hybridoc import tolerances
from hybridoc.errors import EvaluationError, HybridocError
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.solution import Solution, Status
from hybridoc.solvers.transcription.judging import PATH_TOL, Judged, bound_tol
from hybridoc.solvers.transcription.monitor import short_sequence
from hybridoc.solvers.transcription.refine import estimate_text
from hybridoc.solvers.transcription.result import resimulated_names

__all__ = ["cheaper_known", "choose", "claim"]


_CHEAPER_RTOL = tolerances.CHEAPER  # a known control cheaper by more: the result is not-optimal


def claim(
    ocp: HybridOCP,
    j: Judged,
    status: Status,
    message: str,
    sequence: list[str] | None,
    cands: list[list[str]],
    mesh: Any,
) -> tuple[Status, str]:
    """What a feasible candidate that reproduces its events may claim (docs/solvers.rst,
    "dt: what its status claims"): ``not-converged`` when its error estimate is above the
    tolerances (where the default mesh's refinement stopped, or at the user's mesh);
    ``extremal`` for a given
    sequence; ``best-found`` when the discovery did not compare every sequence the problem
    admits (any problem with a guard); ``success`` otherwise (no guard: the only sequence
    is the empty one). Other statuses pass unchanged."""
    if status is not Status.SUCCESS:
        return status, message
    est = j.estimate
    if est is not None and not est["converged"]:
        text = estimate_text(est)
        if mesh is None:
            return Status.NOT_CONVERGED, (
                f"the error estimate is above the tolerance: {text}; the refinement stopped "
                f"at {est.get('stopped', 'its bound')} (try --degree 5 or a --time-limit; "
                "the judged cost is that of the returned control)"
            )
        # the user's mesh is kept, and what it claims is only what its estimate supports
        return Status.NOT_CONVERGED, (
            f"at the given mesh the error estimate is above the tolerance: {text}; without "
            "--mesh dt refines the mesh until it is met (the judged cost is that of the "
            "returned control)"
        )
    if sequence is not None:
        status, message = (
            Status.EXTREMAL,
            (
                f"the transcription's optimum for the given sequence {short_sequence(sequence)}, "
                "not compared with other sequences (without --sequence dt compares its initial "
                "guess's sequences; --method reference searches for the optimum)"
            ),
        )
    elif ocp.guards:
        shown = ", ".join(short_sequence(c) for c in cands[:4])
        more = f" and {len(cands) - 4} more" if len(cands) > 4 else ""
        status, message = (
            Status.BEST_FOUND,
            (
                f"the best of the {len(cands)} event sequence(s) compared ({shown}{more}: the "
                "initial guess's and those with one of its events dropped); other sequences were "
                "not compared, so a cheaper control may exist (--method reference searches for "
                "the optimum; --controls or --sequence start dt elsewhere)"
            ),
        )
    return status, message


def cheaper_known(
    ocp: HybridOCP, j: Judged, guess: Evaluation, initial: Any, differ: list[Judged]
) -> dict[str, Any] | None:
    """The cheapest feasible control dt knows that costs less than ``j``'s (judged, by more
    than ``1e-9`` relative), or ``None``: the initial guess (as simulated), an initial
    Solution's own control, and the controls of candidates whose re-simulation gave other
    events. Feasible: within the bounds, the path and the terminal constraints (and the
    required final mode) by dt's tolerances; a cheaper control that violates them is no
    rival."""
    assert j.ev is not None

    def feasible(ev: Evaluation) -> bool:
        return Judged(j.result, ev, terminal_tol=j.terminal_tol).feasible

    known: list[dict[str, Any]] = []
    is_solution = isinstance(initial, Solution)
    if feasible(guess):
        known.append(
            {
                "source": "the initial solution's controls on the grid"
                if is_solution
                else "the initial guess",
                "cost": float(guess.cost),
                "sequence": resimulated_names(ocp, guess),
            }
        )
    if is_solution:
        try:
            own = evaluate(ocp, initial)
        except HybridocError:
            own = None
        if own is not None and feasible(own):
            known.append(
                {
                    "source": f"the initial solution ({initial.method})",
                    "cost": float(own.cost),
                    "sequence": resimulated_names(ocp, own),
                }
            )
    for d in differ:
        if d.ev is not None and d.feasible:
            known.append(
                {
                    "source": f"the transcription's control for "
                    f"{short_sequence(d.result.sequence)} (re-simulated to other events)",
                    "cost": float(d.ev.cost),
                    "sequence": resimulated_names(ocp, d.ev),
                }
            )
    bound = float(j.ev.cost) * (1 - _CHEAPER_RTOL) - 1e-15 * ocp.scales.cost
    cheaper = [k for k in known if k["cost"] < bound]
    return min(cheaper, key=lambda k: k["cost"]) if cheaper else None


def choose(
    ocp: HybridOCP, matched: list[Judged], differ: list[Judged], tried: list[dict[str, Any]]
) -> tuple[Judged, Status, str]:
    """The candidate to return, its status and message: the first feasible one that
    reproduces its events, else the first that reproduces them, else the one of lowest
    judged cost."""
    feasible = [j for j in matched if j.feasible]
    if feasible:
        return feasible[0], Status.SUCCESS, ""
    if matched:
        ev = matched[0].ev
        assert ev is not None
        parts = []
        if ev.bound_violation > bound_tol(ocp):
            parts.append(
                f"the control bounds by {ev.bound_violation:.3g} (tolerance {bound_tol(ocp):g})"
            )
        if ev.path_violation > PATH_TOL:
            parts.append(
                f"the path constraints by {ev.path_violation:.3g} (tolerance {PATH_TOL:g}; "
                "they hold at the collocation points only: a finer mesh may help)"
            )
        tol = matched[0].terminal_tol
        if ev.terminal_violation > tol:
            parts.append(
                f"the terminal constraints by {ev.terminal_violation:.3g} (tolerance {tol:g}, "
                f"mesh {list(matched[0].result._nlp.mesh)}; the NLP meets them at its "
                "collocated final state: a finer --mesh or a higher --degree may help)"
            )
        message = "the re-simulated control violates " + " and ".join(parts)
        return matched[0], Status.INFEASIBLE, message
    judged = [j for j in differ if j.ev is not None]
    if not judged:
        errors = "; ".join(f"{j.result.sequence}: {j.error}" for j in differ)
        raise EvaluationError(
            f"the judge cannot re-simulate the control of any converged event sequence ({errors})"
        )
    best_j = min(judged, key=lambda j: j.ev.cost)  # type: ignore[union-attr]
    ev = best_j.ev
    assert ev is not None
    message = (
        f"modelled events {best_j.result.sequence} at t = "
        f"{[round(float(t), 9) for t in best_j.result.event_times]} but the re-simulated "
        f"control gives {resimulated_names(ocp, ev)} at t = "
        f"{[round(float(e.time), 9) for e in ev.events]}; no candidate sequence "
        f"reproduced its events (tried {[t['sequence'] for t in tried]})"
    )
    return best_j, Status.EVENTS_DIFFER, message
