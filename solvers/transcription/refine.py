"""Mesh refinement: near misses, terminal constraints, and the error-driven refinement of the
default mesh (the error estimate and its tolerances).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import ConvergenceError, SceneError
from hybridoc.ocp import HybridOCP
from hybridoc.progress import Progress
from hybridoc.solvers.transcription.collocation import lagrange_basis
from hybridoc.solvers.transcription.ipopt import solve_nlp
from hybridoc.solvers.transcription.judging import Judged, judge, try_nudges
from hybridoc.solvers.transcription.monitor import MONITOR
from hybridoc.solvers.transcription.nlp import MAX_NLP_SIZE, PhaseNLP, nlp_for, rounding_level
from hybridoc.solvers.transcription.result import DTResult, event_time_gap, sequence_matches

__all__ = [
    "DEFECT_TOL",
    "MAX_ADAPTIVE_MESH",
    "REFINE_RTOL",
    "error_estimate",
    "estimate_text",
    "jsonable_estimate",
    "judge_or_refine",
    "solve_refined",
]


REFINE_RTOL = tolerances.value("refine")
"""The default mesh is refined until the judged cost of the transcription's control and the
NLP's objective agree within ``REFINE_RTOL * max(1, |J|)`` and, on the first mesh, the
collocation defects between the collocation points stay within :data:`DEFECT_TOL`, or after
a refinement the judged costs of the last two meshes agree within the same
(``info["error_estimate"]``)."""


DEFECT_TOL = tolerances.value("defect")
"""The largest collocation defect between collocation points that the default mesh accepts:
``h_e |x'(t_m) - f(x(t_m), u(t_m))|`` at the midpoints ``t_m`` of consecutive nodes of each
element, relative to ``max(1, max |x_i|)`` on the phase (the state's local error over one
element)."""


MAX_ADAPTIVE_MESH = 256
"""The most elements per phase the error-driven refinement of the default mesh reaches (the
default's 4 elements doubled six times); past it, or past :data:`MAX_NLP_SIZE`, a result
whose error estimate is still above the tolerances is ``not-converged``."""


_MAX_ADAPTIONS = 12  # refinements of one candidate


_NEAR_MISS = 1e-3  # event-time mismatch (relative to T) that a finer mesh may fix


_TERMINAL_REFINEMENTS = 4  # mesh doublings (default mesh 4 -> up to 64) for terminal constraints


_NEAR_MISS_REFINEMENTS = 3  # mesh doublings (default mesh 4 -> up to 32) for a near miss


def _split_mesh(
    coarse: PhaseNLP, split: Sequence[np.ndarray | None]
) -> tuple[list[int], list[np.ndarray | None]]:
    """The mesh with the elements ``split[k]`` (booleans per element of phase ``k``; ``None``:
    none) of each phase halved: its element counts and shares (``None`` where equal)."""
    mesh, fractions = [], []
    for k, which in enumerate(split):
        frac = coarse.fractions[k]
        if which is None or not np.any(which):
            mesh.append(coarse.mesh[k])
            fractions.append(frac)
            continue
        if frac is None and np.all(which):
            mesh.append(2 * coarse.mesh[k])  # uniform doubling: still equal elements
            fractions.append(None)
            continue
        shares = coarse.shares(k)
        new = np.concatenate(
            [[x / 2, x / 2] if w else [x] for x, w in zip(shares, which, strict=True)]
        )
        mesh.append(int(new.size))
        fractions.append(new)
    return mesh, fractions


def solve_refined(
    ocp: HybridOCP,
    r: DTResult,
    verbose: bool,
    phases: Sequence[int] | None = None,
    split: Sequence[np.ndarray | None] | None = None,
) -> DTResult:
    """Re-solve ``r``'s sequence on a finer mesh, started from ``r``'s state and control
    polynomials: the elements ``split`` (per phase, booleans per element) halved, or with
    ``split=None`` every element of the ``phases`` (default: every phase)."""
    coarse = r._nlp
    d, rad = coarse.d, coarse.rad
    if split is None:
        which = range(coarse.P) if phases is None else set(phases)
        split = [np.full(m, k in which) for k, m in enumerate(coarse.mesh)]
    fine_mesh, fine_fractions = _split_mesh(coarse, split)
    uniform = all(f is None for f in fine_fractions)
    fine = nlp_for(ocp, coarse.guards, d, fine_mesh, None if uniform else fine_fractions)
    h, Xc, Uc = coarse.unpack(r._w)
    X, U = [], []
    for k in range(coarse.P):
        Mc, Mf = coarse.mesh[k], fine.mesh[k]
        if coarse.fractions[k] is None and fine.fractions[k] is None:
            loc = (np.arange(Mf)[:, None] + rad.tau[None, 1:]).ravel() / Mf  # in (0, 1]
            sigma = np.concatenate([[0.0], loc]) * Mc  # node positions in coarse elements
            e = np.clip(np.floor(sigma).astype(int), 0, Mc - 1)
            s = sigma - e
        else:
            fe, ce = fine.edges(k), coarse.edges(k)
            loc = (fe[:-1, None] + fine.shares(k)[:, None] * rad.tau[None, 1:]).ravel()
            pos = np.concatenate([[0.0], loc])  # node positions in the phase, 0 to 1
            e = np.clip(np.searchsorted(ce, pos, side="right") - 1, 0, Mc - 1)
            s = (pos - ce[e]) / coarse.shares(k)[e]
        bx = lagrange_basis(rad.tau, s)  # (n, d + 1)
        cols = e[:, None] * d + np.arange(d + 1)[None, :]
        X.append(np.einsum("nr,xnr->xn", bx, Xc[k][:, cols]))
        su, eu = s[1:], e[1:]
        bu = lagrange_basis(rad.tau[1:], su)  # (n, d)
        ucols = eu[:, None] * d + np.arange(d)[None, :]
        U.append(fine.clip_controls(np.einsum("nj,unj->un", bu, Uc[k][:, ucols])))
    V = coarse.unpack_v(r._w) if coarse.reset_events else None
    return solve_nlp(fine, fine.pack(h, X, U, V), list(r.sequence), verbose)


def _refine_terminal(
    ocp: HybridOCP, j: Judged, verbose: bool, progress: Progress
) -> tuple[Judged, bool]:
    """At the default mesh, a candidate that reproduces its events but whose re-simulated
    final state misses the terminal constraints by more than the tolerance (the
    collocation's error, which the NLP does not see) is solved again with twice the
    elements, up to :data:`_TERMINAL_REFINEMENTS` times: Radau collocation's error at the
    element ends falls as ``h^(2d-1)``. Returns the last judged candidate that still
    reproduces its events and whether it was refined."""
    refined = False
    for _ in range(_TERMINAL_REFINEMENTS):
        assert j.ev is not None
        if j.ev.terminal_violation <= j.terminal_tol:
            break
        progress.stage(
            f"refining the {len(j.result.sequence)}-event candidate (twice the mesh): the "
            f"judged terminal violation is {j.ev.terminal_violation:.1e}"
        )
        try:
            rf = solve_refined(ocp, j.result, verbose)
        except (ConvergenceError, SceneError):  # SceneError: beyond MAX_NLP_SIZE
            break
        jf = judge(ocp, rf, j.terminal_tol)
        if jf.ev is None or not sequence_matches(ocp, rf, jf.ev):
            break
        j, refined = jf, True
    return j, refined


def judge_or_refine(
    ocp: HybridOCP,
    r: DTResult,
    mesh: Any,
    verbose: bool,
    progress: Progress,
    terminal_tol: float,
) -> tuple[Judged, bool, bool]:
    """The judged candidate, whether it reproduces its events, and whether it was refined:
    at the default mesh, a near miss (the same events at times off by a little) is solved
    again with twice the elements, since a finer mesh may fix it, up to
    :data:`_NEAR_MISS_REFINEMENTS` times while the event-time gap shrinks (a stance phase
    of the hopper, an oscillation, needs mesh 16), and so is a candidate that misses its
    terminal constraints (:func:`_refine_terminal`)."""
    j = judge(ocp, r, terminal_tol)
    ok = j.ev is not None and sequence_matches(ocp, r, j.ev)
    if not ok and j.ev is not None:
        # missed by a hair where the next phase's control stops the approach: judged again
        # with the approaching control extended past the event
        nudged = try_nudges(ocp, r, terminal_tol)
        if nudged is not None:
            j, ok = nudged[0], True
    if ok and mesh is None:
        refined = False
        if ocp.has_terminal_constraints:
            j, refined = _refine_terminal(ocp, j, verbose, progress)
        j, adapted = _adapt(ocp, j, verbose, progress)
        return j, ok, refined or adapted
    if ok:  # the user's mesh: its error estimate is reported, not acted on
        j.estimate = error_estimate(ocp, j)
        return j, ok, False
    if mesh is not None or j.ev is None:
        return j, ok, False
    gap = event_time_gap(ocp, r, j.ev)
    if gap is None or not gap <= _NEAR_MISS * ocp.horizon:
        return j, ok, False
    best: Judged | None = None
    for _ in range(_NEAR_MISS_REFINEMENTS):
        progress.stage(f"refining the {len(r.sequence)}-event candidate (twice the mesh)")
        try:
            rf = solve_refined(ocp, r if best is None else best.result, verbose)
        except (ConvergenceError, SceneError):  # SceneError: beyond MAX_NLP_SIZE
            break
        jf = judge(ocp, rf, terminal_tol)
        if jf.ev is None:
            break
        gap_f = event_time_gap(ocp, jf.result, jf.ev)
        if best is not None and (gap_f is None or not gap_f < gap):
            break  # no progress: the previous refinement stands
        best = jf
        if gap_f is None or sequence_matches(ocp, jf.result, jf.ev):
            break
        gap = gap_f
    if best is None:
        return j, ok, False
    ok_f = sequence_matches(ocp, best.result, best.ev)
    if ok_f and ocp.has_terminal_constraints:
        best = _refine_terminal(ocp, best, verbose, progress)[0]
    if ok_f:
        best = _adapt(ocp, best, verbose, progress)[0]
    return best, ok_f, True


def _defects(ocp: HybridOCP, r: DTResult) -> list[np.ndarray]:
    """Per phase and element, the largest collocation defect between the collocation points:
    ``h_e |x'(t_m) - f(x(t_m), u(t_m))|`` at the midpoints ``t_m`` of consecutive nodes of
    every element (``x`` the state polynomial, ``u`` the control polynomial clipped into the
    bounds), each state relative to ``max(1, max |x_i|)`` on the phase. The NLP makes the
    defect zero at the collocation points only; between them it is the local error of one
    element, which shrinks as ``h^(d+1)`` where the solution is smooth."""
    nlp = r._nlp
    d, rad = nlp.d, nlp.rad
    mids = 0.5 * (rad.tau[:-1] + rad.tau[1:])
    bx = lagrange_basis(rad.tau, mids)  # (d, d + 1)
    dbx = np.zeros_like(bx)
    for j in range(d + 1):
        others = np.delete(rad.tau, j)
        poly = np.poly1d(others, r=True) / np.prod(rad.tau[j] - others)
        dbx[:, j] = np.polyder(poly)(mids)
    bu = lagrange_basis(rad.tau[1:], mids)  # (d, d)
    lo = np.asarray(ocp.u_min, dtype=float)[:, None]
    hi = np.asarray(ocp.u_max, dtype=float)[:, None]
    h = np.diff(np.concatenate([[0.0], r.event_times, [r.horizon]]))
    f = ocp.f.map(d)
    sx, off = ocp.scales.state_array, ocp.scales.offset_array
    out = []
    for k in range(nlp.P):
        M = nlp.mesh[k]
        shares = nlp.shares(k)
        X, U = r.states[k], r.controls[k]
        # max(1, max |x_i|) in the state's units: sigma_i max(1, max |(x_i - s0_i) / sigma_i|)
        if ocp.scales.is_identity:
            scale = np.maximum(1.0, np.max(np.abs(X), axis=1))
        else:
            scale = sx * np.maximum(1.0, np.max(np.abs(X - off[:, None]) / sx[:, None], axis=1))
        per = np.zeros(M)
        for e in range(M):
            he = h[k] * float(shares[e])
            Xe, Ue = X[:, e * d : e * d + d + 1], U[:, e * d : e * d + d]
            xm = Xe @ bx.T
            fm = np.asarray(f(xm, np.clip(Ue @ bu.T, lo, hi)), dtype=float)
            dev = np.abs(Xe @ dbx.T - he * fm) / scale[:, None]
            per[e] = float(np.max(dev, initial=0.0))
        out.append(per)
    return out


def error_estimate(ocp: HybridOCP, j: Judged, previous_cost: float | None = None) -> dict[str, Any]:
    """The error estimate of a judged candidate that reproduces its events: what the default
    mesh's refinement acts on (:data:`REFINE_RTOL`, :data:`DEFECT_TOL`).

    Returns
    -------
    dict
        ``cost_gap``: ``|judged cost - NLP objective| / max(1, |J|)``; ``refinement_change``:
        the same of the judged costs of this mesh and the previous one (``None`` before a
        refinement); ``defects``: :func:`_defects` per phase; ``event_time_gap``: the
        largest gap between modelled and re-simulated event times; ``phases``: the phases
        whose defect is above :data:`DEFECT_TOL` (where to refine); ``converged``: the cost
        gap within :data:`REFINE_RTOL` and, on the first mesh, the defects within
        :data:`DEFECT_TOL`, after a refinement the change within :data:`REFINE_RTOL`.
    """
    r, ev = j.result, j.ev
    assert ev is not None
    scale = max(ocp.scales.cost, abs(float(ev.cost)))  # max(1, |J|) in the cost's units
    gap = abs(float(ev.cost) - r.nlp_cost) / scale
    change = None if previous_cost is None else abs(float(ev.cost) - previous_cost) / scale
    per_element = _defects(ocp, r)
    defects = [float(np.max(x, initial=0.0)) for x in per_element]
    phases = [k for k, x in enumerate(defects) if not x <= DEFECT_TOL]
    time_gap = event_time_gap(ocp, r, ev)
    # REFINE_RTOL, or above the rounding of a problem far from its origin (whose judged
    # cost carries that rounding, which no mesh removes)
    rtol = max(REFINE_RTOL, 100 * rounding_level(ocp))
    if change is None:  # the first mesh: its defects must be small too
        converged = gap <= rtol and not phases
    else:  # refined: the last two meshes agree (the defects only say where to refine)
        converged = gap <= rtol and change <= rtol
    return {
        "tolerance": rtol,
        "cost_gap": gap,
        "refinement_change": change,
        "defects": defects,
        "event_time_gap": time_gap,
        "phases": phases,
        "converged": bool(converged),
        "mesh": list(r._nlp.mesh),
        "_split": [~(x <= DEFECT_TOL) for x in per_element],
    }


def estimate_text(est: dict[str, Any]) -> str:
    """The error estimate for a message."""
    rtol = est.get("tolerance", REFINE_RTOL)
    parts = [f"judged cost vs NLP objective {est['cost_gap']:.2e} (relative)"]
    if est.get("refinement_change") is not None:
        parts.append(f"change from the previous mesh {est['refinement_change']:.2e}")
    parts.append(f"largest collocation defect {max(est['defects'], default=0.0):.2e}")
    return (
        ", ".join(parts) + f" at mesh {est['mesh']} (tolerances {rtol:g}, {rtol:g}, {DEFECT_TOL:g})"
    )


def _adapt(ocp: HybridOCP, j: Judged, verbose: bool, progress: Progress) -> tuple[Judged, bool]:
    """Refine the mesh of a candidate that reproduces its events until its error estimate
    (:func:`error_estimate`) is within the tolerances, as h-adaptive direct methods do:
    the elements whose collocation defects are too large are halved (every element when
    only the costs disagree), the refined NLP is solved from the coarse solution and
    judged, and the estimate compares it with the previous mesh too. Stops at
    :data:`MAX_ADAPTIVE_MESH` elements per phase, after :data:`_MAX_ADAPTIONS` refinements,
    at :data:`MAX_NLP_SIZE`, or when a refined NLP fails or its control no longer
    reproduces the events; ``j.estimate`` then says what was not met (``stopped``).
    Returns the last candidate and whether it was refined."""
    refined = False
    previous: float | None = None
    previous_gap: float | None = None
    stalled = 0  # consecutive refinements that left the settled cost's gap as it was
    for _ in range(_MAX_ADAPTIONS):
        est = error_estimate(ocp, j, previous)
        j.estimate = est
        if est["converged"]:
            return j, refined
        change = est["refinement_change"]
        settled = change is not None and change <= est["tolerance"]
        if settled and previous_gap is not None and est["cost_gap"] >= 0.9 * previous_gap:
            stalled += 1
        else:
            stalled = 0
        if stalled >= 2:
            # the judged cost has settled across meshes while the NLP's objective stays as
            # far from it, twice: finer meshes do not close that gap (at a grazing contact
            # the refinement went on for 12 rounds, 115 s, to the same numbers)
            est["stopped"] = (
                "the judged cost settled across meshes while the NLP objective stays "
                f"{est['cost_gap']:.2e} from it (two refinements did not close it)"
            )
            return j, refined
        previous_gap = est["cost_gap"]
        nlp = j.result._nlp
        if est["phases"]:
            split = [x if k in est["phases"] else None for k, x in enumerate(est["_split"])]
        else:  # only the costs disagree: every element
            split = [np.ones(m, dtype=bool) for m in nlp.mesh]
        counts, _ = _split_mesh(nlp, split)
        split = [None if n > MAX_ADAPTIVE_MESH else x for n, x in zip(counts, split, strict=True)]
        phases = [k for k, x in enumerate(split) if x is not None and np.any(x)]
        if not phases:
            est["stopped"] = f"the mesh bound MAX_ADAPTIVE_MESH = {MAX_ADAPTIVE_MESH} per phase"
            return j, refined
        monitor = MONITOR.get()
        if monitor is not None and monitor.expired():
            raise monitor.stop(f"while refining the mesh ({estimate_text(est)})")
        progress.stage(
            f"refining phase(s) {phases} of the {len(j.result.sequence)}-event candidate: "
            + estimate_text(est)
        )
        try:
            rf = solve_refined(ocp, j.result, verbose, split=split)
        except SceneError:
            est["stopped"] = f"the NLP size bound MAX_NLP_SIZE = {MAX_NLP_SIZE}"
            return j, refined
        except ConvergenceError as exc:
            est["stopped"] = f"IPOPT failed on the refined mesh ({exc})"
            return j, refined
        jf = judge(ocp, rf, j.terminal_tol)
        if jf.ev is None or not sequence_matches(ocp, rf, jf.ev):
            nudged = None if jf.ev is None else try_nudges(ocp, rf, j.terminal_tol)
            if nudged is None:
                est["stopped"] = "the refined mesh's control does not reproduce the events"
                return j, refined
            jf = nudged[0]
            jf.nudge = nudged[1]
        assert j.ev is not None
        previous = float(j.ev.cost)
        j, refined = jf, True
    # the last refinement's candidate, judged by the same estimate
    est = error_estimate(ocp, j, previous)
    j.estimate = est
    if not est["converged"]:
        est["stopped"] = f"the most refinements, {_MAX_ADAPTIONS}"
    return j, refined


def jsonable_estimate(est: dict[str, Any]) -> dict[str, Any]:
    """An error estimate with plain floats and lists, for ``info``."""
    out = {k: v for k, v in est.items() if not k.startswith("_")}
    out["defects"] = [float(x) for x in est["defects"]]
    for key in ("cost_gap", "refinement_change", "event_time_gap"):
        if out.get(key) is not None:
            out[key] = float(out[key])
    return out
