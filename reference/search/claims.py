"""What the reference claims, and the words it says it in (part of
:mod:`hybridoc.reference.search`).

The proof of the global optimum from the search's coverage (:func:`proof`), the checks of an
answer (a reset's control that is not a minimum, the path constraints along the judge's
re-simulation, impacts that coalesce or coincide), and the Solution with its coverage
(:func:`finish`; :func:`coverage_line`, :func:`families_line` for the command line).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import ConvergenceError, HybridocError
from hybridoc.evaluation import Evaluation
from hybridoc.methods import problem_features
from hybridoc.ocp import HybridOCP
from hybridoc.reference.options import MAX_EVENTS
from hybridoc.reference.result import ReferenceResult, reference_control
from hybridoc.reference.search.book import (
    LACKS,
    MAX_PROOF_DEPTH,
    OPT_RTOL,
    Book,
    Known,
    Run,
    exhaustive_length,
    is_convex,
    is_feasible,
    lacks_reason,
    n_events,
    path_violation,
    source_lacks,
    too_long,
)
from hybridoc.reference.units import cost_shown as _J
from hybridoc.solution import Solution, Status

FAILED_SHOWN = 4
"""The failed sequences ``info["coverage"]["failed"]`` lists (all are counted)."""


PROOF_STARTS = 2
"""Distinct starts of Newton that must reach the optimum's extremal (the same cost, to
:data:`START_RTOL`) for a ``success``: one start can land on a worse stationary point of
the right sequence."""


def coverage_line(coverage: dict[str, Any] | None) -> str:
    """One line of what the reference covered (``info["coverage"]``): the sources, the
    sequences proposed and solved, the exhaustive length and whether the budget stopped it."""
    if not coverage:
        return "(none recorded)"
    ex = coverage.get("exhaustive_length")
    failed = coverage.get("failed") or {}
    if ex is not None:
        reach = f"every sequence of up to {n_events(ex)}"
    elif "enumeration" in coverage.get("sources", ()):
        reach = "no length covered exhaustively"
    else:
        reach = "no enumeration"
    text = (
        f"{coverage['proposed']} sequence(s) proposed, {coverage['solved']} solved, "
        f"{coverage['pruned']} pruned by bounds"
        + (
            f", {failed['count']} failed ("
            + "; ".join(",".join(q) or "no event" for q in failed.get("sequences", []))
            + (", ..." if failed["count"] > len(failed.get("sequences", [])) else "")
            + ")"
            if failed.get("count")
            else ""
        )
        + f"; {reach}; sources: {', '.join(coverage['sources']) or 'none'}"
    )
    if coverage.get("budget_stopped"):
        text += f"; stopped by the budget of {coverage['budget_s']:g} s"
    if coverage.get("stopped"):
        text += f"; stopped: {coverage['stopped']}"
    if "proven" in coverage:
        text += "; optimum proven" if coverage["proven"] else "; not proven"
    unsupported = [
        f"{row['name']} ({row['reason'].removeprefix('not run: ')})"
        for row in coverage.get("skipped_sources") or []
        if "budget" not in row["reason"]
    ]
    if unsupported:
        text += "; not run: " + ", ".join(unsupported)
    return text


def families_line(coverage: dict[str, Any] | None) -> str:
    """The best cost of each sequence family (the sequences of one number of events) that
    the reference solved, cheapest marked: ``"0 events 1.64; 2 events 0.16107 (best)"``."""
    families = (coverage or {}).get("families") or []
    if not families:
        return "(none solved)"
    best = min(f["best_cost"] for f in families)
    return "; ".join(
        f"{n_events(f['events'])} {f['best_cost']:.6g}"
        + (" (best)" if f["best_cost"] == best else "")
        for f in families
    )


def summary_lines(sol: Solution) -> list[tuple[str, str]]:
    """What ``hybridoc solve`` prints about a reference solution: the HMP residual, the
    coverage and the settings."""
    lines = []
    if "residual" in sol.info:
        lines.append(("residual", f"{sol.info['residual']:.2e} (HMP, max norm)"))
    if "coverage" in sol.info:
        lines.append(("coverage", coverage_line(sol.info["coverage"])))
        lines.append(("families", families_line(sol.info["coverage"])))
    settings = ", ".join(f"{k} {v}" for k, v in sol.settings.items() if v is not None)
    if settings:
        lines.append(("settings", settings))
    return lines


def proof(run: Run, book: Book, best: ReferenceResult) -> tuple[bool, str]:
    """``(proven, text)``: whether the coverage proves ``best`` the global optimum, and
    the words that say how, or what is missing.

    Proven means all of: every feasible sequence of up to ``len(best) + 1`` events was
    solved (an extremal found) or excluded by a valid lower bound (``exhaustive_length``);
    no extremal of those lengths that is cheaper than ``best`` fails to re-simulate to its
    own events (that sequence's optimum, with the extra contacts avoided, would be unknown);
    every longer sequence that a control met has (a feasible known control, a
    re-simulation) has an extremal or is excluded by a bound; and the optimum's extremal
    was reached from at least :data:`PROOF_STARTS` distinct
    starts of Newton that agree (:data:`START_RTOL`). Sequences longer than
    ``len(best) + 1`` are not covered: the proof is of the search's claim, not of an
    infinite enumeration (docs/reference.rst, "What success means")."""
    k = len(best.sequence)
    need = k + 1
    ex = exhaustive_length(book)
    why: list[str] = []
    if ex is not None and ex >= need:
        covered = (
            f"every feasible sequence of up to {n_events(ex)} solved or excluded by a bound "
            f"(the optimum has {n_events(k)})"
        )
    else:
        reach = (
            "no length covered" if ex is None else f"every sequence of up to {n_events(ex)} covered"
        )
        nxt = 0 if ex is None else ex + 1
        why.append(f"{reach}; the best has {n_events(k)}; {_uncovered(run, book, nxt)}")
        covered = ""
    bound = best.cost * (1 - OPT_RTOL) - 1e-15
    for key, res in sorted(book.results.items(), key=lambda kv: kv[1].cost):
        if res.cost >= bound:
            break
        if len(key) <= need and not book.verify(key):
            why.append(
                f"the extremal of {list(key) or 'no event'} costs {_J(res.cost):.10g}, less, but "
                "does not re-simulate to its own events: that sequence's optimum with the other "
                "contacts avoided is not known"
            )
            break
    # a control met (known, or an extremal's re-simulation) with a longer sequence shows
    # that sequence reachable: one whose extremal was not found leaves the claim open (a
    # break whose relaxed one-strike extremal re-simulates to the cascade)
    met = {tuple(k.sequence) for k in book.rivals()}
    met |= {tuple(sim.sequence) for sim in book.resimulated.values()}
    open_ = sorted(
        (
            q
            for q in met
            if need < len(q) <= MAX_EVENTS and q not in book.results and q not in book.pruned
        ),
        key=lambda q: (len(q), q),
    )
    if open_:
        why.append(
            f"{len(open_)} longer sequence(s) that a control met has, without an extremal "
            f"(the first: {','.join(open_[0])})"
        )
    key = tuple(best.sequence)
    n = book.agreeing_starts(key)
    if is_convex(book.ocp, key) and n >= 1:
        n = max(n, PROOF_STARTS)  # one extremal: the unique minimum
    if n < PROOF_STARTS:
        others = sorted(
            {f"{_J(c):.10g}" for c in book.start_costs.get(key, ()) if c != best.cost}
            - {f"{_J(best.cost):.10g}"}
        )
        why.append(
            f"its extremal was reached from {n} start(s) of Newton, {PROOF_STARTS} needed"
            + (f" (other starts reached {', '.join(others)})" if others else "")
        )
    if why:
        return False, "; ".join(why)
    if is_convex(book.ocp, key):
        return True, f"{covered}; its extremal is the unique minimum (no event: a convex problem)"
    return True, f"{covered}; its extremal reached from {n} starts of Newton"


def _uncovered(run: Run, book: Book, length: int) -> str:
    """Why the sequences of ``length`` events are not all covered (for :func:`proof`)."""
    if length > book.depth or length >= len(book.enumerated):
        if book.depth >= MAX_PROOF_DEPTH:
            return f"sequences of {n_events(length)} are beyond the enumeration (MAX_PROOF_DEPTH)"
        return f"sequences of {n_events(length)} were not enumerated"
    keys = book.enumerated[length]
    left = [k for k in keys if k not in book.results and k not in book.pruned]
    failed = [k for k in left if k in book.reasons]
    untried = len(left) - len(failed)
    parts = []
    if failed:
        first = ",".join(failed[0]) or "no event"
        parts.append(f"{len(failed)} failed (the first: {first})")
    if untried:
        stop = f"the budget of {run.budget:g} s was spent" if book.budget_stopped else "not reached"
        parts.append(f"{untried} not solved ({stop})")
    return f"sequences of {n_events(length)} not all solved: " + ", ".join(parts)


def touch_note(book: Book) -> str:
    """Where a sequence failed at a touch point of a pure state constraint (the constraint
    met at one instant, which the reference does not model): the words that say so; else
    empty."""
    for key, why in book.reasons.items():
        text = touch_reason(why)
        if text:
            return f"{text} (with the events {list(key)}); use method 'dt'"
    return ""


def touch_reason(why: str | None) -> str:
    """The touch point a sequence's failure reasons name (its first), without the advice
    to use dt; else empty."""
    at = -1 if why is None else why.find("pure state constraint row")
    if why is None or at < 0 or "touch point" not in why:
        return ""
    end = why.find("use method 'dt'", at)
    return why[at : end if end >= 0 else len(why)].rstrip("; ")


def extremal_path_violation(ocp: HybridOCP, best: ReferenceResult) -> float:
    """The path constraints' largest violation along the judge's re-simulation of the
    extremal's ``u(t)`` (:func:`path_violation`; 0 without path constraints)."""
    if ocp.path is None:
        return 0.0
    from hybridoc.callable_eval import evaluate_callable

    u, breakpoints = reference_control(best)
    try:
        ev = evaluate_callable(
            best.ocp, u, breakpoints=breakpoints, event_controls=best.event_controls
        )
    except HybridocError:
        return math.inf
    return path_violation(ocp, ev, u)


EVENT_CONTROL_PROBE = 1e-3
"""How far, relative to ``1 + |v|``, :func:`event_control_rival` moves a reset's own
control on each side (besides trying its bounds)."""


def event_control_rival(ocp: HybridOCP, best: ReferenceResult) -> dict[str, Any] | None:
    """A control cheaper than the extremal ``best`` found by moving one reset control
    ``v_k`` (``u(t)`` kept), or ``None``.

    The shooting's conditions on ``v_k`` are first order (stationary inside the bounds, the
    right sign at a bound), which a maximum meets too; the judge is the arbiter: each
    component ``v_k,i`` a reset reads is moved by :data:`EVENT_CONTROL_PROBE` ``(1 +
    |v|)`` either way and to each finite bound, and a feasible move (:func:`is_feasible`) with
    the same events that the judge finds cheaper by more than ``1e-9`` relative is
    returned: ``{"source", "cost", "sequence", "event", "component", "value"}``.
    """
    V0 = best.event_controls
    if V0 is None:
        return None
    from hybridoc.callable_eval import evaluate_callable

    u, breakpoints = reference_control(best)

    def judge(V: np.ndarray) -> Evaluation | None:
        try:
            return evaluate_callable(best.ocp, u, breakpoints=breakpoints, event_controls=V)
        except HybridocError:
            return None

    base = judge(V0)
    if base is None:
        return None
    lo, hi = best.system.core.v_bounds
    for k, comps in enumerate(best.system.core.v_comps):
        for i in comps:
            v = float(V0[k, i])
            step = EVENT_CONTROL_PROBE * (1.0 + abs(v))
            trials = {v - step, v + step, float(lo[i]), float(hi[i])}
            for w in sorted(x for x in trials if math.isfinite(x) and x != v):
                if not lo[i] <= w <= hi[i]:
                    continue
                V = np.array(V0, dtype=float)
                V[k, i] = w
                ev = judge(V)
                if (
                    ev is not None
                    and ev.sequence == base.sequence
                    and ev.cost < base.cost - OPT_RTOL * abs(base.cost)
                    and is_feasible(ocp, ev)
                ):
                    return {
                        "source": f"the extremal with the control of event {k + 1}'s reset "
                        f"u[{i}] = {w:.6g} instead of {v:.6g}",
                        "cost": float(ev.cost),
                        "sequence": list(ev.sequence),
                        "event": k,
                        "component": i,
                        "value": w,
                    }
    return None


def check_coalescing(ocp: HybridOCP, c: Known, best: ReferenceResult) -> None:
    """A cheaper known control whose impacts nearly coincide without commuting: the
    optimum lies at a simultaneous impact, an error."""
    pair = _coalescing(ocp, c)
    if pair is None:
        return
    a, b, gap = pair
    raise ConvergenceError(
        f"no optimal control exists within the impulsive model: the cheapest control "
        f"found ({c.source}, cost {_J(c.cost):.10g}) has the impacts {a!r} and {b!r} only "
        f"{gap:.2g} apart, and no extremal with them in order exists: the optimum lies "
        "at a simultaneous impact whose jumps do not commute, which the model does not "
        "define. Perturb the scene slightly so that the contacts happen one after the "
        f"other (the best well-defined extremal found costs {_J(best.cost):.10g})"
    )


def finish(
    ocp: HybridOCP,
    run: Run,
    book: Book,
    best: ReferenceResult,
    status: Status,
    message: str,
    cheapest: dict[str, Any] | None,
    landscape: list[dict[str, Any]] | None,
) -> Solution:
    """The Solution: the best extremal with what was tried, known and used."""
    candidates = [
        {"sequence": row["sequence"], "result": row["verdict"] if row["cost"] is None else
         f"cost {row['cost']:.12g} ({row['verdict']})", "origin": row["origin"]}
        for row in book.landscape()
    ]  # fmt: skip
    info: dict[str, Any] = {
        "verified": bool(run.verify or run.seq is None),
        "candidates": candidates,
        "known_controls": [
            {"source": k.source, "cost": k.cost, "sequence": k.sequence}
            # only where feasibility is in question (terminal or path constraints, a free
            # final time)
            | ({"feasible": k.feasible} if problem_features(ocp) or ocp.path is not None else {})
            for k in book.known
        ],
        "sources": list(book.sources),
        "warm_starts": [s.name for s in book.starters],
    }
    unused = [s for s in run.starters if s not in book.starters]
    if unused:
        info["warm_starts_skipped"] = [
            {"name": s.name, "reason": lacks_reason(source_lacks(ocp, s))} for s in unused
        ]
    if cheapest is not None:
        info["cheaper"] = cheapest
    if landscape is not None:
        info["landscape"] = landscape
    best.coverage = _coverage(run, book, best)
    if best.coverage.get("proven") and status is not Status.SUCCESS:
        # the coverage would prove it, but the answer is beaten or infeasible
        best.coverage["proven"] = False
        best.coverage.pop("proof", None)
        best.coverage["why_not_proven"] = f"the answer is {status.value}"
    if best.coverage["budget_stopped"] and status is Status.SUCCESS and not message:
        ex = best.coverage["exhaustive_length"]
        message = (
            f"the optimum: the budget of {run.budget:g} s stopped the enumeration after it "
            f"had covered every sequence of up to {ex} events, as the proof needs"
        )
    elif status is Status.BEST_FOUND and best.coverage["budget_stopped"]:
        message += "; --budget gives it more time"
    sol = best.to_solution(timings={"verify_time_s": book.verify_time}, info=info)
    sol.settings = {
        "tol": run.tol, "rtol": run.rtol, "sequence": run.seq, "search": run.search,
        "multistart": run.multistart, "budget": run.budget,
    }  # fmt: skip
    sol.timings = {"solve_time_s": time.perf_counter() - run.t_start, **sol.timings}
    return sol.set_status(status, message)


def _coverage(run: Run, book: Book, best: ReferenceResult | None = None) -> dict[str, Any]:
    """``info["coverage"]``: what the search covered (:func:`solve_reference`), and whether
    it proves ``best`` the optimum (:func:`proof`)."""
    # the cheapest extremal of each length that re-simulates to its own events
    families: dict[int, tuple[float, tuple[str, ...]]] = {}
    for key, res in sorted(book.results.items(), key=lambda kv: kv[1].cost):
        if len(key) not in families and book.verify(key):
            families[len(key)] = (float(res.cost), key)
    attempted = {k for k in [*book.results, *book.reasons] if k not in book.pruned}
    attempted -= {k for k, why in book.reasons.items() if why == too_long(len(k))}
    failed = sorted((k for k in attempted if k not in book.results), key=lambda k: (len(k), k))
    return {
        "sources": [row["name"] for row in book.sources if "skipped" not in row],
        "proposed": len(book.proposed | set(book.results) | set(book.reasons)),
        "attempted": len(attempted),
        "solved": len(book.results),
        "pruned": len(book.pruned),
        "depth": book.depth,
        "exhaustive_length": exhaustive_length(book),
        "failed": {"count": len(failed), "sequences": [list(k) for k in failed[:FAILED_SHOWN]]},
        "budget_s": run.budget,
        "budget_stopped": bool(book.budget_stopped),
        "time_limit_s": run.time_limit,
        "stopped": book.stopped or None,
        **_proof_fields(run, book, best),
        "family": "the number of events",
        "families": [
            {"events": k, "best_cost": c, "sequence": list(key)}
            for k, (c, key) in sorted(families.items())
        ],
        **_skipped_sources(book),
    }


def _proof_fields(run: Run, book: Book, best: ReferenceResult | None) -> dict[str, Any]:
    """``proven`` and ``proof`` (how) or ``why_not_proven`` for ``info["coverage"]``."""
    if best is None:
        return {"proven": False, "why_not_proven": "no answer"}
    if run.seq is not None:
        return {
            "proven": False,
            "why_not_proven": "a given sequence: its extremal, not compared with every other "
            "sequence" + (" (the search without it decides the status)" if run.search else ""),
        }
    if book.stopped:
        return {"proven": False, "why_not_proven": f"the search was stopped ({book.stopped})"}
    proven, text = proof(run, book, best)
    return {"proven": True, "proof": text} if proven else {"proven": False, "why_not_proven": text}


def _skipped_sources(book: Book) -> dict[str, Any]:
    """``{"skipped_sources": [{"name", "reason"}]}``: the sources not run because they do not
    honour the problem's features (:func:`source_lacks`), or ``{}`` (a source the budget
    stopped is only in ``info["sources"]``)."""
    rows = [
        {"name": r["name"], "reason": r["skipped"]}
        for r in book.sources
        if "skipped" in r and LACKS in r["skipped"]
    ]
    return {"skipped_sources": rows} if rows else {}


def extremal_message(seq: list[str], verify: bool, search: int | None) -> str:
    """The message of an ``extremal``: what it is and what it is not."""
    checked = "" if verify else " (not re-simulated by the judge: verify=False)"
    if search is not None:
        return f"the HMP extremal of the given sequence {seq}{checked}"
    return (
        f"the HMP extremal of the given sequence {seq}{checked}, not compared with other "
        "sequences (without --sequence, or with --search K, the reference looks for the "
        "optimum)"
    )


def _coalescing(ocp: HybridOCP, k: Known) -> tuple[str, str, float] | None:
    """Two consecutive events of a known control that nearly coincide and whose jumps do
    not commute: ``(guard a, guard b, time apart)``, else ``None``."""
    ev = k.evaluation
    if ev is None or len(ev.events) < 2:
        return None
    from hybridoc.events import commute_defect
    from hybridoc.kernels import kernels

    num = kernels(ocp).numeric()
    for e1, e2 in zip(ev.events[:-1], ev.events[1:], strict=True):
        gap = e2.time - e1.time
        if gap > 1e-4 * ocp.horizon or e1.guard == e2.guard:
            continue
        s = np.asarray(e1.state_before, dtype=float)
        ra, rb = num.reset(e1.guard), num.reset(e2.guard)
        ga, gb = np.asarray(ra(s)[0], dtype=float), np.asarray(rb(s)[0], dtype=float)
        ab = np.asarray(ra(gb)[0], dtype=float)
        ba = np.asarray(rb(ga)[0], dtype=float)
        # the judge's test: only the components the jumps change, each at its own scale (a
        # far body must not lend its size to the tolerance)
        defect = commute_defect(ab, ba, s, ga, gb, floor=ocp.scales.state_array)
        if defect > tolerances.value("commute"):
            return e1.name, e2.name, gap
    return None


def check_simultaneous(book: Book, best: ReferenceResult | None) -> None:
    """An extremal cheaper than every verified one whose events coincide without an order
    means the problem has no optimum within the impulsive model: a clear error."""
    bound = math.inf if best is None else best.cost * (1 - OPT_RTOL)
    for key, (ok, msg) in sorted(book.verdicts.items(), key=lambda kv: book.results[kv[0]].cost):
        res = book.results[key]
        if ok or res.cost >= bound or "same instant" not in msg:
            continue
        raise ConvergenceError(
            f"the cheapest extremal ({_J(res.cost):.10g}, events {list(key)}) has events that "
            "coincide in time without commuting jumps: the optimum of this problem lies at a "
            "simultaneous impact, which the impulsive model does not define (controls that "
            "separate the impacts by a little come arbitrarily close to that cost). Perturb the "
            "scene so that the contacts happen one after the other"
            + (
                ""
                if best is None
                else f"; the best well-defined extremal found costs {_J(best.cost):.10g}"
            )
        )
