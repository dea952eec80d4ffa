"""IPOPT on a transcribed NLP, and its result collected: the phases, the controls and the
costates from the multipliers.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc.errors import ConvergenceError
from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.solvers.transcription.guess import initial_point
from hybridoc.solvers.transcription.monitor import MONITOR, short_sequence
from hybridoc.solvers.transcription.nlp import PhaseNLP, nlp_for, terminal_count
from hybridoc.solvers.transcription.options import DTOptions, checked_degree, checked_mesh
from hybridoc.solvers.transcription.result import DTResult

__all__ = ["solve_dt_sequence", "solve_nlp"]


def _found_horizon(ocp: HybridOCP, h: np.ndarray) -> float:
    """The final time of the phase durations ``h``: ``T`` when fixed; for a free final time
    their sum, clipped into the bounds (IPOPT may relax a bound by about ``1e-8``)."""
    if ocp.horizon_bounds is None:
        return ocp.horizon
    lo, hi = ocp.horizon_bounds
    return float(min(max(float(np.sum(h)), lo), hi))


def solve_nlp(nlp: PhaseNLP, w0: np.ndarray, sequence: list[str], verbose: bool) -> DTResult:
    """Run IPOPT on a transcribed NLP from ``w0`` and collect the result (reporting to the
    :func:`solve_dt` run in progress, if any)."""
    ocp, P = nlp.ocp, nlp.P
    monitor = MONITOR.get()
    solver = nlp.solver(verbose)
    assert nlp.callback is not None
    nlp.callback.monitor, nlp.callback.iteration = monitor, 0
    try:
        res = solver(x0=w0, lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg)
    finally:
        nlp.callback.monitor = None
    stats = solver.stats()
    status = str(stats.get("return_status", ""))
    if monitor is not None and monitor.interrupted:
        # CasADi turns SIGINT inside IPOPT into NonIpopt_Exception_Thrown and swallows the
        # KeyboardInterrupt: the run's handler (solve_dt) set the flag
        raise KeyboardInterrupt
    if monitor is not None and status == "User_Requested_Stop" and monitor.expired():
        raise monitor.stop(
            f"in IPOPT iteration {nlp.callback.iteration} of the {P - 1}-event sequence "
            f"{short_sequence(sequence)} ({nlp.n_w} variables, {nlp.n_g} constraints)"
        )
    if not stats.get("success", False) and status != "Solved_To_Acceptable_Level":
        raise _not_converged(nlp, res, stats, status, sequence)
    w = np.asarray(res["x"]).ravel()
    lam_g = np.asarray(res["lam_g"]).ravel()
    h, X, U = nlp.unpack(w)
    U = [nlp.clip_controls(Uk) for Uk in U]  # IPOPT may relax a bound by ~1e-8
    times = nlp.node_times(h)
    d, rad = nlp.d, nlp.rad

    # costates: phase start from the initial-condition / link multiplier, then Radau points
    ct: list[np.ndarray] = []
    cs: list[np.ndarray] = []
    lam0 = -nlp.mult(lam_g, "x0")[0]
    for k in range(P):
        start = lam0 if k == 0 else -nlp.mult(lam_g, f"link{k - 1}")[0]
        coll = nlp.mult(lam_g, f"coll{k}")
        lam_nodes = [
            -(c.reshape((ocp.nx, d), order="F") / rad.w[None, :]) for c in coll
        ]  # per element (nx, d)
        ct.append(times[k][:1])
        cs.append(start[None, :])
        ct.append(times[k][1:])
        cs.append(np.concatenate([ln.T for ln in lam_nodes], axis=0))
    jumps = np.array([nlp.mult(lam_g, f"guard{k}")[0][0] for k in range(P - 1)])
    path = [np.abs(m).max() for k in range(P) for m in nlp.mult(lam_g, f"path{k}") if m.size]
    bounds = [np.array([0.0])]
    for k in range(P):
        bounds.append(times[k][d::d])
    element_bounds = np.concatenate(bounds)
    event_controls = None
    if nlp.reset_events:
        V = nlp.clip_controls(nlp.unpack_v(w))
        event_controls = np.array([U[k][:, -1] for k in range(P - 1)], dtype=float)
        for i, k in enumerate(nlp.reset_events):
            event_controls[k] = V[:, i]
    return DTResult(
        sequence=list(sequence),
        nlp_cost=float(res["f"]) * nlp.cs if nlp.scaled else float(res["f"]),
        event_times=np.cumsum(h)[:-1],
        node_times=times,
        states=X,
        control_times=[t[1:] for t in times],
        controls=U,
        costate_times=np.concatenate(ct),
        costates=np.concatenate(cs, axis=0),
        jump_multipliers=jumps,
        lambda0=lam0,
        horizon=_found_horizon(ocp, h),
        iterations=int(stats.get("iter_count", -1)),
        status=status,
        active_path=float(max(path)) if path else 0.0,
        element_bounds=element_bounds,
        _nlp=nlp,
        _w=w,
        event_controls=event_controls,
    )


def _not_converged(
    nlp: PhaseNLP, res: dict[str, Any], stats: dict[str, Any], status: str, sequence: list[str]
) -> ConvergenceError:
    """The error of an NLP that IPOPT did not solve (its status, the constraint violation
    where it stopped and what to try)."""
    ocp = nlp.ocp
    g = np.asarray(res["g"]).ravel()
    viol = float(np.max(np.maximum(nlp.lbg - g, g - nlp.ubg), initial=0.0))
    what = "did not converge"
    hint = "try another initial guess or event sequence"
    if status in ("Infeasible_Problem_Detected", "Restoration_Failed"):
        # IPOPT's infeasibility is local: it stopped at a point that minimises the
        # constraint violation nearby, which proves nothing about the constraints
        what = (
            "stopped at a point of local infeasibility (IPOPT converged to a local "
            "minimum of the constraint violation: a local failure, not a proof that "
            "the constraints cannot be met)"
        )
        hint = (
            "start it elsewhere: another --controls guess (one whose simulation has these "
            "events, e.g. another method's solution), a finer --mesh, or another --sequence"
        )
    if terminal_count(ocp) or ocp.horizon_bounds is not None:
        hint = (
            "the terminal constraints may be unreachable with these events, bounds and "
            "final time; " + hint
        )
    return ConvergenceError(
        f"direct transcription for sequence {list(sequence)} {what} (IPOPT: {status}, "
        f"constraint violation {viol:.2e} after {int(stats.get('iter_count', -1))} "
        f"iterations); {hint}"
    )


def solve_dt_sequence(
    ocp: HybridOCP,
    sequence: Sequence[str],
    *,
    guess: Evaluation,
    guess_controls: np.ndarray,
    degree: int = DTOptions.degree,
    mesh: int | Sequence[int] | None = DTOptions.mesh,
    verbose: bool = DTOptions.verbose,
) -> DTResult:
    """Solve the transcribed NLP for one event sequence.

    Parameters
    ----------
    ocp
        The problem.
    sequence
        Guard names of the events, in time order.
    guess, guess_controls
        A simulated trajectory and its ``(N, nu)`` controls, to initialise the phases.
    degree
        Collocation degree ``d`` (state polynomial degree), 1 to :data:`MAX_DEGREE`.
    mesh
        Elements per phase: one number for all phases or one per phase, 1 to
        :data:`MAX_MESH` each.
    verbose
        Print IPOPT's log.

    Returns
    -------
    DTResult

    Raises
    ------
    ConvergenceError
        IPOPT did not converge.
    """
    names = [g.name for g in ocp.guards]
    guards = [names.index(s) for s in ocp.check_sequence(sequence)]
    degree = checked_degree(degree)
    P = len(guards) + 1
    mesh_list = checked_mesh(mesh, P)
    nlp = nlp_for(ocp, guards, degree, mesh_list)
    w0, _ = initial_point(nlp, guess, guess_controls)
    return solve_nlp(nlp, w0, list(sequence), verbose)
