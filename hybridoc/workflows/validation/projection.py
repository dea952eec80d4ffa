"""The reference projected onto a method's representation of a control
(:func:`representable`), the same projection refined (:func:`refined_projection`), and the
reference extremal of a method's own event sequence (:func:`local_gap`): the yardsticks of
:func:`~hybridoc.workflows.validation.crossval`. What a method's control can express is
its :attr:`~hybridoc.methods.Method.representation`; no method is named here."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from hybridoc.errors import HybridocError, SceneError
from hybridoc.methods import METHODS, REFERENCE_METHOD, Method, solve
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.progress import ProgressLike
from hybridoc.solution import Solution
from hybridoc.workflows.validation.measures import (
    event_comparison,
    event_key,
    relative,
)

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP

__all__ = [
    "grid_projection",
    "local_gap",
    "refined_projection",
    "representable",
    "terminal_violation",
]


def grid_projection(ocp: HybridOCP, ref: Solution | None) -> dict[str, Any]:
    """The judged cost of the reference's cell averages on the problem's N-step grid."""
    if ref is None or ocp.free_horizon:
        return {"grid_cost": None, "grid_gap_relative": None}
    try:
        grid = ref.to_grid(problem=ocp)
        cost = float(grid.cost)
    except HybridocError as exc:
        return {"grid_cost": None, "grid_gap_relative": None, "grid_error": str(exc)}
    out = {"grid_cost": cost, "grid_gap_relative": relative(cost, ref.cost)}
    violation = terminal_violation(ocp, grid)
    if violation is not None:
        out["grid_terminal_violation"] = violation
    return out


def representable(
    problem: ProblemLike,
    method: str,
    ref: Solution,
    *,
    options: Mapping[str, Any] | None = None,
    progress: ProgressLike = None,
) -> dict[str, Any]:
    """The reference projected onto ``method``'s representation of a control, and its cost.

    A method's gap to the reference mixes two things: what its representation of the
    control cannot express (discretisation) and how far it is from the best it could
    express (disagreement: a local optimum, a failure to converge, a wrong gradient). The
    projection is the second's yardstick:

    ``dt``
        The transcription re-solved from the reference (its control and its event sequence
        as the initial guess) with ``options`` (the same mesh and degree): the optimum of
        dt's own discretisation near the reference, judged like any dt answer. Holding the
        reference on dt's mesh instead would give a control that dt's NLP never optimises
        (its quadrature and collocation differ from the judge's exact cost). It bounds
        nothing: dt may land below it or above it.
    any other method
        The reference's control averaged over the cells of the N-step grid and judged: a
        control of the grid, so an upper bound on the best cost the grid can represent,
        not that best (the best piecewise-constant control may be cheaper: a negative gap
        of the method to it is no finding).

    Either projection is a faithful yardstick only when it keeps the reference's events
    (``representable_sequence_matches``): one that loses them (a control that stops short
    of a guard on re-simulation) measures the loss, not the discretisation.

    Parameters
    ----------
    problem
        Any problem.
    method
        A registered method name.
    ref
        The reference Solution.
    options
        The method's options (``dt``: ``mesh``, ``degree``).
    progress
        Passed to a re-solve.

    Returns
    -------
    dict
        ``representable`` (what it is, in words), ``representable_cost``,
        ``discretisation_gap_relative`` (``(J_proj - J*) / |J*|``), ``representable_sequence``
        (its events' guards) and ``representable_sequence_matches``; ``representable_cost``
        is ``None`` with ``representable_error`` when it could not be built. On a problem
        with terminal constraints or a final mode the grid projection also reports its
        judged ``representable_terminal_violation``: the projection does not keep the
        constraints, so a method that meets them may cost more than it, or less.
    """
    ocp = as_ocp(problem)
    m = METHODS[method]
    if m.representation == "continuous":
        opt = m.resolution_option
        what = f"{method} re-solved from the reference on its own {opt or 'discretisation'}"
        keep = {k: v for k, v in (options or {}).items() if k in m.projection_options}
        try:
            best = _resolved_from(ocp, m, ref, keep, progress)
        except HybridocError as exc:
            return _no_representable(what, str(exc))
        out = _projection_fields(what, best, ref)
        if opt is not None:
            out[f"representable_{opt}"] = [int(x) for x in best.info.get(opt) or []]
        return out
    what = f"the reference's cell averages on the N = {ocp.steps} grid"
    if ocp.free_horizon:
        return _no_representable(what, "a free final time has no fixed grid to project on")
    try:
        grid = ref.to_grid(problem=ocp)
    except HybridocError as exc:
        return _no_representable(what, str(exc))
    out = _projection_fields(what, grid, ref)
    violation = terminal_violation(ocp, grid)
    if violation is not None:
        out["representable_terminal_violation"] = violation
    return out


def _resolved_from(
    ocp: HybridOCP, m: Method, ref: Solution, options: Mapping[str, Any], progress: ProgressLike
) -> Solution:
    """A ``"continuous"`` method re-solved from the reference: its control as the initial
    guess and, when the method takes one, its event sequence."""
    seq = {"sequence": ref.sequence} if m.takes("sequence") else {}
    return solve(ocp, m.name, initial=ref, **seq, progress=progress, **options)


def _projection_fields(what: str, proj: Solution, ref: Solution) -> dict[str, Any]:
    cost = float(proj.cost)
    return {
        "representable": what,
        "representable_cost": cost,
        "discretisation_gap_relative": relative(cost, ref.cost),
        "representable_sequence": [event_key(e) for e in proj.events],
        "representable_sequence_matches": event_comparison(proj.events, ref.events)[
            "sequence_matches"
        ],
    }


def refined_projection(
    problem: ProblemLike,
    method: str,
    ref: Solution,
    *,
    options: Mapping[str, Any] | None = None,
    progress: ProgressLike = None,
) -> dict[str, Any]:
    """:func:`representable` on a grid (``dt``: a mesh) twice as fine: check
    ``"refinement"`` of :func:`crossval`.

    For a piecewise-constant method the reference's cell averages on the ``2 N`` grid; for
    ``dt`` the transcription re-solved from the reference with twice the elements of the
    mesh it used (its ``mesh`` option, else the mesh its solution reports). A gap that is the
    discretisation's shrinks (an order-1 error halves) and the projection keeps the
    reference's events; a lost event or a local optimum does neither.

    Returns
    -------
    dict
        ``refined`` (what it is), ``refined_cost``, ``refined_gap_relative`` and
        ``refined_sequence_matches``; ``refined_gap_relative`` ``None`` with
        ``refined_error`` when it could not be built.
    """
    from hybridoc.ocp import MAX_STEPS

    ocp = as_ocp(problem)
    opts = dict(options or {})
    m = METHODS[method]
    try:
        if m.representation == "continuous":
            opt = m.resolution_option
            if opt is None:
                raise SceneError(f"{method} declares no resolution option to refine")
            keep = {k: v for k, v in opts.items() if k in m.projection_options and k != opt}
            res = opts.get(opt)
            if res is None:  # the resolution of the projection at the method's options
                first = _resolved_from(ocp, m, ref, keep, progress)
                res = max(int(x) for x in first.info.get(opt) or [first.settings[opt]])
            res = 2 * (max(int(x) for x in res) if isinstance(res, Sequence) else int(res))
            what = f"{method} re-solved from the reference on {opt} {res}"
            fine = _resolved_from(ocp, m, ref, {**keep, opt: res}, progress)
        else:
            steps = 2 * ocp.steps
            what = f"the reference's cell averages on the N = {steps} grid"
            if steps > MAX_STEPS or ocp.free_horizon:
                raise SceneError(f"no grid of {steps} steps")
            fine = ref.to_grid(problem=ocp.replace(steps=steps))
    except HybridocError as exc:
        return {
            "refined": f"{method}'s projection refined",
            "refined_cost": None,
            "refined_gap_relative": None,
            "refined_sequence_matches": None,
            "refined_error": " ".join(str(exc).split()),
        }
    return {
        "refined": what,
        "refined_cost": float(fine.cost),
        "refined_gap_relative": relative(float(fine.cost), ref.cost),
        "refined_sequence_matches": event_comparison(fine.events, ref.events)["sequence_matches"],
    }


def terminal_violation(ocp: HybridOCP, sol: Solution) -> float | None:
    """The judged terminal violation of ``sol`` (a :meth:`Solution.to_grid` projection) on a
    problem with terminal constraints or a final mode (the grid projection of ``J*`` does
    not keep them: a method that meets them may cost more than it, so a gap to it is no
    finding), else ``None``."""
    if not (ocp.has_terminal_constraints or ocp.final_mode is not None):
        return None
    return float(sol.info["terminal_violation"])  # Solution.to_grid's judged violation


def _no_representable(what: str, why: str) -> dict[str, Any]:
    return {
        "representable": what,
        "representable_cost": None,
        "discretisation_gap_relative": None,
        "representable_sequence": None,
        "representable_sequence_matches": None,
        "representable_error": " ".join(why.split()),
    }


def local_gap(
    problem: ProblemLike, sol: Solution, ref: Solution, *, progress: ProgressLike = None
) -> dict[str, Any]:
    """The gap of ``sol`` to the reference extremal with ``sol``'s own event sequence.

    Local methods (gradient descent above all) converge to the HMP extremal of the basin
    they start in, which need not be the lowest-cost one the reference finds (on
    multiple-collision a three-event extremal lies 4.6% below the paper's two-event one).
    This measures a method against the extremal of its own mode sequence (solved, with
    ``progress`` passed to the reference, when it is not the reference's own).

    Returns
    -------
    dict
        ``local_reference_cost``, ``local_reference_sequence`` and
        ``cost_gap_local_relative``; ``local_reference_error`` instead when the reference
        has no verified extremal for that sequence.
    """
    sequence = sol.sequence
    if event_comparison(sol.events, ref.events)["sequence_matches"]:
        local = ref
    else:
        try:
            local = solve(
                problem, REFERENCE_METHOD, sequence=sequence, initial=sol, progress=progress
            )
        except HybridocError as exc:
            return {
                "local_reference_cost": None,
                "local_reference_sequence": sequence,
                "cost_gap_local_relative": None,
                "local_reference_error": str(exc),
            }
    return {
        "local_reference_cost": float(local.cost),
        "local_reference_sequence": sequence,
        "cost_gap_local_relative": float((sol.cost - local.cost) / abs(local.cost)),
    }
