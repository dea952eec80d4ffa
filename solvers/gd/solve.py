"""gd's entry points: :func:`solve_gd` (the options as keywords), :func:`run_gd` (as one
:class:`~hybridoc.solvers.gd.options.GDOptions`), the dispatch to hops, multi-start,
continuation or the augmented Lagrangian, and the stop at a time limit or an interrupt."""

from __future__ import annotations

import dataclasses
import signal
import time
from typing import Any

import numpy as np

from hybridoc.errors import OptionError
from hybridoc.evaluator import evaluate
from hybridoc.methods import options_from_keywords, options_signature
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solution import Solution, Status
from hybridoc.solvers.gd.descent import continuation, initial_controls, run_settings
from hybridoc.solvers.gd.hops import hop
from hybridoc.solvers.gd.limits import WATCH, OutOfTime, Watch
from hybridoc.solvers.gd.loss import make_loss
from hybridoc.solvers.gd.options import (
    GDOptions,
    checked_options,
)
from hybridoc.solvers.gd.starts import run_multistart
from hybridoc.solvers.gd.terminal import solve_terminal
from hybridoc.solvers.threads import flag_interrupts


def solve_gd(
    problem: ProblemLike,
    *,
    initial: Any = None,
    progress: ProgressLike = None,
    **options: Any,
) -> Solution:
    """Minimise the discrete objective by gradient descent through the simulation.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`): a built-in name, a Scene, a
        HybridOCP, a ``.toml`` path or ``file.py:function``.
    initial
        Starting controls: ``None`` (the problem's guess), an ``(N, nu)`` array or a
        Solution.
    progress
        ``True`` for a progress meter on stderr, or a :class:`~hybridoc.progress.Progress`
        (``False``/``None``, the default: quiet). One meter serves the whole run: a stage
        per smoothing weight, hop round and multi-start phase, a count per iteration.
    contact, toi
        Disc scenes: the contact model, a name of
        :data:`hybridoc.solvers.contacts.CONTACT_MODELS` or a
        :class:`~hybridoc.solvers.contacts.ContactModel` with its own options
        (``LCP(toi="both")``, ``contact_model("compliant", stiffness=2e4)``), and the
        time-of-impact correction of an impulse model given by name (default ``"both"``).
    integrator
        ``"exact"`` or ``"symplectic-euler"`` (disc scenes only; the paper's). Default: exact
        for impulse models with both TOI corrections and for generic problems, symplectic
        Euler otherwise (the other settings have no exact form).
    optimizer
        ``"gd"`` (plain gradient descent, as in the paper), ``"adam"`` or ``"lbfgs"``
        (default: :class:`~hybridoc.solvers.optimizers.LBFGS`, a numpy port of
        ``torch.optim.LBFGS`` with its strong-Wolfe line search, as gd has always run it:
        one trial step of ``lr`` per iteration, taken when it lowers the loss,
        :data:`~hybridoc.solvers.optimizers.GD_LINE_SEARCH_EVALS`; SciPy's L-BFGS-B when
        the problem has control bounds). All run on numpy arrays: on the compiled path a
        solve imports no torch.
    smoothing
        Continuation weights ``mu_1 > mu_2 > ...``: before the real problem, solve it with the
        penalty ``mu sum_n |u_{n+1} - u_n|^2 / dt`` (about ``mu int |du/dt|^2 dt``) added, for
        each ``mu`` in turn, each stage starting from the previous result (``iters`` iterations
        per stage). The loss of piecewise-constant controls has a kink wherever an event
        crosses a grid time at which the control jumps, and gradient methods stall there; the
        penalty weakens those kinks so that the events first move to the right times.
        Default: :data:`DEFAULT_SMOOTHING` for ``lbfgs``, none for ``gd`` and ``adam``.
    iters, lr
        Iterations and learning rate; defaults from :func:`default_settings`.
    starts
        Multi-start: ``starts`` initial controls (the guess, perturbations of it, random smooth
        controls, controls aimed at each body and wall; :mod:`hybridoc.solvers.multistart`)
        descend together, one batched rollout per iteration, on a coarse grid; the best
        distinct results are refined by the single-start method at full resolution and the
        best of them returned. ``info["starts"]`` lists every start's result (its loss on
        the coarse grid; the judge's cost and events of each distinct optimum).
    seed
        Seed of the random starts (and of the hops' perturbations).
    hops
        Batched restarts after the descent, for losses with kinks and shallow local minima
        (any loss kinks where an event crosses a grid time, the symplectic Euler loss
        wherever a contact moves to another step, and gradient descent stalls at a kink that
        is not a minimum, or in a shallow local minimum beside a lower one; on the exact
        integrator a converged descent is taken past its kinks anyway, see Returns): in
        each round, :data:`HOP_BATCH` perturbations of the best control, at sizes spread
        geometrically from 1e-3 to 1 of its largest value, descend together by the batched
        L-BFGS of :mod:`hybridoc.solvers.multistart`; the lowest replaces the best when it is
        lower. Stops after ``hops`` rounds or :data:`HOP_PATIENCE` rounds without
        improvement. ``info["hops"]`` lists the rounds. Compiled path only.
    callback
        Called as ``callback(iteration, loss, controls)`` after every iteration; a true
        return value stops the optimisation.
    path
        ``"auto"`` (the compiled CasADi path where the model's CasADi step serves the scene,
        else torch), ``"compiled"`` or ``"torch"`` (disc scenes).
    max_step
        ``lbfgs`` only: the largest change of any control value in one iteration (longer
        steps are shortened and the curvature history is reset); default: no limit.
    path_weight
        Weight of the quadratic penalty on path-constraint violations (problems with
        ``path`` constraints).
    terminal_tol, terminal_rho, terminal_iters
        Problems with terminal constraints or a free final time (module notes):
        the largest terminal violation the judge may find for a success, the augmented
        Lagrangian's initial penalty and its number of outer iterations at most.
    time_limit
        Seconds of wall time after which the run stops where it is (checked at every
        evaluation of the loss) and returns its best iterate so far, judged, as
        ``not-converged`` (``info["stopped"] = "time-limit"``); default: no limit. A
        ``KeyboardInterrupt`` (Ctrl-C, SIGINT) does the same (``"interrupted"``); a second
        one during the judging of that iterate propagates.

    Returns
    -------
    hybridoc.solution.Solution
        Method ``"gd"``; the controls of the last iterate (of the best iterate if the loss
        became non-finite); ``cost`` is the judge's continuous cost of those controls.
        ``info`` holds the final discrete ``loss``, ``iterations``, ``message`` and
        ``converged``; ``status`` is ``success`` (the optimiser met its convergence test:
        L-BFGS could make no further progress, or the loss stalled, to :data:`STALL_RTOL`
        over :func:`stall_window` iterations, at the iteration limit), ``not-converged``
        (the iteration limit without meeting it, ``iters=0``, a stop by the callback, a
        non-finite or rising loss, a stall at a kink, ``time_limit`` or an interrupt) or
        ``infeasible``. Kinks: with the exact integrator and unbounded controls, a converged
        descent with an event within :data:`KINK_BAND` of a step of a grid time is taken on
        by a nonsmooth BFGS (:func:`past_kinks`), and ``success`` needs its certificate
        (:data:`KINK_GTOL`); otherwise the status is ``not-converged``, "stalled at a kink:
        event k pinned at grid time t_j", and ``info["kinks"]`` holds the events near grid
        times, the certificate and the iterations. ``info["stages"]`` (the smoothing stages)
        and ``info["final_stage"]`` give each stage's iterations, loss evaluations and
        optimisation time; ``iterations``, ``loss_evaluations``, ``ms_per_iteration`` and
        ``timings["optimization_time_s"]`` are over all of them.
        ``settings`` holds the contact model's own
        (:meth:`~hybridoc.solvers.contacts.ContactModel.settings`) and the run's.

    Raises
    ------
    hybridoc.errors.OptionError
        For options out of range or that do not apply to the problem (one line).
    hybridoc.resources.ResourceError
        For sizes (``starts``, ``iters``, ``hops``) whose memory estimate exceeds
        :func:`memory_limit` (a :class:`~hybridoc.errors.SceneError`).
    TypeError
        For a keyword that is no option.
    """
    opts = options_from_keywords(GDOptions, options, "solve_gd")
    return run_gd(problem, opts, initial=initial, progress=progress)


solve_gd.__signature__ = options_signature(solve_gd, GDOptions)  # type: ignore[attr-defined]


def run_gd(
    problem: ProblemLike,
    options: GDOptions | None = None,
    *,
    initial: Any = None,
    progress: ProgressLike = None,
) -> Solution:
    """:func:`solve_gd` with its options as one :class:`GDOptions` (``None``: the defaults).

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`).
    options
        The options, checked on construction; their problem-dependent defaults are filled
        in here (:func:`checked_options`).
    initial, progress
        As in :func:`solve_gd`.

    Returns
    -------
    hybridoc.solution.Solution
        As :func:`solve_gd`.
    """
    ocp = as_ocp(problem)
    opts = checked_options(ocp, GDOptions() if options is None else options)
    watch = Watch(opts.time_limit)
    token = WATCH.set(watch)
    # an interrupt CasADi swallows inside a loss call is still seen at the next check
    previous = flag_interrupts(watch)
    try:
        with progress_scope(progress, "gd") as meter:
            try:
                return _dispatch(ocp, opts, initial, meter)
            except (OutOfTime, KeyboardInterrupt) as exc:
                why = "time-limit" if isinstance(exc, OutOfTime) else "interrupted"
                return _stopped_solution(ocp, opts, initial, watch, why)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        WATCH.reset(token)


def _stopped_solution(
    ocp: HybridOCP, opts: GDOptions, initial: Any, watch: Watch, why: str
) -> Solution:
    """The best iterate of a run stopped at its time limit or by an interrupt, judged, as
    ``not-converged``."""
    elapsed = time.perf_counter() - watch.t0
    if why == "time-limit":
        head = f"stopped at the time limit of {watch.time_limit:g} s"
    else:
        head = f"interrupted after {elapsed:.3g} s"
    if watch.u is None:
        u, horizon = initial_controls(ocp, initial), None
        if ocp.has_bounds:
            u = np.clip(u, ocp.u_min, ocp.u_max)
        text = f"{head}, before the first iterate: the controls are the initial guess"
    else:
        u, horizon = watch.u, watch.horizon
        hint = "raise the time limit" if why == "time-limit" else "let it run"
        text = (
            f"{head}: returning the best iterate so far (discrete loss {watch.loss:.10g}, "
            f"after {watch.iterations} iteration(s)); {hint} to converge"
        )
    judged = ocp.replace(horizon=horizon) if horizon is not None and ocp.free_horizon else ocp
    ev = evaluate(judged, u)
    info: dict[str, Any] = {
        "loss": watch.loss if watch.u is not None else float("nan"),
        "iterations": watch.iterations,
        "loss_evaluations": watch.evaluations,
        "nan_stop": False,
        "diverged": False,
        "converged": False,
        "message": text,
        "stopped": why,
    }
    if horizon is not None and ocp.free_horizon:
        info["horizon"] = float(horizon)
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings={**run_settings(ocp, opts, opts.path), "time_limit": opts.time_limit},
        timings={"solve_time_s": elapsed, "optimization_time_s": elapsed},
        info=info,
        arrays={"loss_history": np.array(watch.history, dtype=float)},
    )
    return sol.set_status(Status.NOT_CONVERGED, text)


def _dispatch(ocp: HybridOCP, opts: GDOptions, initial: Any, progress: Progress) -> Solution:
    """Hops around a multi-start or a continuation, as ``opts`` (checked) says; the
    augmented Lagrangian for terminal constraints or a free final time."""
    if ocp.has_terminal_constraints or ocp.free_horizon:
        return solve_terminal(ocp, opts, initial, progress)
    if opts.hops:
        t_hop = time.perf_counter()
        loss_obj, used_path = make_loss(
            ocp, opts.contact, opts.integrator, opts.path, opts.path_weight
        )
        if not hasattr(loss_obj, "value_and_grad_batch"):
            raise OptionError(
                f"hops run batched rollouts on the compiled path; the {used_path} path of "
                f"contact {opts.contact.label!r} has none"
            )
        base = _dispatch(ocp, dataclasses.replace(opts, hops=0), initial, progress)
        return hop(ocp, base, loss_obj, opts, t_hop, progress)
    if opts.starts > 1:
        return run_multistart(ocp, opts, progress)
    return continuation(ocp, opts, initial, progress)
