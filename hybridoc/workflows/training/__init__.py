"""Feedback policies: training through the closed loop, and its exact gradient.

A feedback policy ``u = pi(t, s)`` is judged by :func:`hybridoc.evaluate` with
``policy=pi`` (zero-order hold: sampled at the grid times from the exact state and held over
the interval). This module trains such policies and differentiates that judgement.

:func:`mlp_policy`
    A small multilayer perceptron ``(t, s) -> u`` whose input normalisation and output
    offset and scale come from the problem, so that an untrained policy acts like the
    initial guess: a disc scene's positions, targets and initial control, or, for any other
    :class:`~hybridoc.HybridOCP`, the spread of its initial-state distribution, the states
    its initial guess visits and its control bounds.
:func:`train_policy`
    Trains a policy on a batch of initial states by gradient descent (Adam or L-BFGS) on
    the mean closed-loop cost. On a disc scene, through the closed-loop rollout of the
    differentiable disc simulator
    (:meth:`hybridoc.solvers.simulator.Simulator.rollout_policy`), with the paper's
    time-of-impact corrections (``toi="both"``) or without them (``toi="none"``). On any
    other problem, through the judge's event-exact closed loop and its exact discrete
    adjoint (:func:`closed_loop_cost`): the loss is the judged cost itself, and the event
    times' sensitivity (the saltation matrix) is part of the gradient, which is what
    ``toi="both"`` means there; the judge has no rollout without it, so other ``toi``
    values are refused on such problems.
:class:`TensorAdam`, :func:`cosine_annealing_lrs`
    The optimiser steps of the training, without ``torch.optim`` (whose first optimiser
    imports ``torch._dynamo``, seconds per process): ``torch.optim.Adam``'s arithmetic on
    the parameters in place and ``CosineAnnealingLR``'s learning rates, the same iterates
    bit for bit on the CPU. L-BFGS is the numpy port of ``torch.optim.LBFGS``
    (:func:`~hybridoc.solvers.optimizers.lbfgs_torch_step`) on the flattened parameters.
:func:`training_draws`
    The initial states to train on: draws of the problem's distribution (a scene's
    ``[distribution]`` table or :attr:`HybridOCP.distribution <hybridoc.HybridOCP>`) with
    a seed other than the one :func:`~hybridoc.workflows.policies.validate_policy` judges
    on by default.
:func:`closed_loop_cost`
    The judge's event-exact closed-loop cost as a differentiable torch scalar: its backward
    pass is the exact gradient with respect to the policy's parameters (and the initial
    states), by the discrete adjoint of the closed loop (below).

The exact closed-loop gradient
    With zero-order hold the closed loop is the discrete-time system
    ``s_{n+1} = F_n(s_n, u_n)``, ``u_n = pi(t_n, s_n; theta)``, where ``F_n`` is the exact
    flow over grid interval ``n`` with every event's jump. The open-loop adjoint of the judge
    (:func:`hybridoc.evaluator.adjoint`: transposed segment Jacobians, and the hybrid minimum
    principle's jump relation at every event, i.e. the saltation matrix) gives
    ``dF_n/ds^T mu`` and ``dF_n/du^T mu``. The closed-loop costate adds the policy's
    reaction at every grid time,

    .. math::

        g_n = \\frac{\\partial F_n}{\\partial u}^\\top \\mu_{n+1}
              + \\frac{\\partial c_n}{\\partial u}, \\qquad
        \\mu_n = \\frac{\\partial F_n}{\\partial s}^\\top \\mu_{n+1}
                 + \\frac{\\partial c_n}{\\partial s}
                 + \\frac{\\partial \\pi}{\\partial s}^\\top g_n,

    from ``mu_N = grad phi(s_N)``, and ``dJ/dtheta = sum_n (d pi/d theta)^T g_n``,
    ``dJ/ds_0 = mu_0``. The Jacobians ``d pi/ds`` come from torch in one batched call, and
    the parameter gradient from one vector-Jacobian product through the policy. The gradient
    is that of the judge's cost wherever the event sequence does not change under the
    perturbation (not at grazing contacts).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, EvaluationError, SceneError
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.progress import ProgressLike, progress_scope
from hybridoc.solvers.simulator import Simulator
from hybridoc.workflows.training.gradient import (
    ClosedLoopGradient,
    closed_loop_cost,
    closed_loop_gradient,
    judged_loss,
)
from hybridoc.workflows.training.gradient import numpy_twin as _numpy_twin
from hybridoc.workflows.training.gradient import x0_tensor as _x0_tensor
from hybridoc.workflows.training.optim import FlatParameters as _FlatParameters  # noqa: F401
from hybridoc.workflows.training.optim import Steps as _Steps
from hybridoc.workflows.training.optim import TensorAdam, cosine_annealing_lrs
from hybridoc.workflows.training.optim import train_adam as _train_adam
from hybridoc.workflows.training.optim import train_lbfgs as _train_lbfgs
from hybridoc.workflows.training.policy import SCALE_DRAWS, MLPPolicy, mlp_policy  # noqa: F401

__all__ = [
    "ENGINES",
    "ClosedLoopGradient",
    "MLPPolicy",
    "TensorAdam",
    "TrainResult",
    "closed_loop_cost",
    "closed_loop_gradient",
    "cosine_annealing_lrs",
    "judged_loss",
    "mlp_policy",
    "train_policy",
    "training_draws",
]

OPTIMIZERS = ("adam", "lbfgs")


def _is_disc(problem: ProblemLike) -> bool:
    """Whether ``problem`` is a disc scene (the differentiable simulator's model)."""
    from hybridoc.problems import load_problem, scene_of

    obj = load_problem(problem) if isinstance(problem, str | Path) else problem
    return scene_of(obj) is not None


# ---------------------------------------------------------------------------- training
ENGINES = ("simulator", "judge")
"""What :func:`train_policy` trains through: the differentiable disc simulator (disc scenes)
or the judge's event-exact closed loop with its exact adjoint (every other problem)."""


@dataclass
class TrainResult:
    """What :func:`train_policy` returns.

    Attributes
    ----------
    policy
        The trained policy (the same object that was passed in, trained in place).
    losses
        The mean closed-loop loss at each iteration (before its update): the simulator's
        discrete objective (``engine`` ``"simulator"``) or the judge's cost (``"judge"``).
    final_loss
        The loss of the parameters the policy ends with.
    seconds
        Wall time of the training.
    toi, contact, integrator
        The simulator's settings; with the judge, ``"both"`` (the event times'
        sensitivity is in the gradient), ``"exact"`` and ``"judge"``.
    engine
        One of :data:`ENGINES`.
    message
        Empty, or why the training stopped before its last iteration (the judge could not
        simulate the closed loop of some initial state: the parameters are then the best
        ones judged).
    infeasible
        Engine ``"judge"``: how many training draws' closed loops under the final policy
        violate the problem's control bounds, path or terminal constraints
        (:attr:`Evaluation.feasible <hybridoc.Evaluation>`); the loss is the cost of
        controls the problem does not allow when it is not 0 (the training minimises the
        cost alone). ``None`` for the simulator (not judged).
    feasibility
        Engine ``"judge"``: per training draw, the judge's ``bound_violation``,
        ``path_violation``, ``terminal_violation`` (NaN where it could not simulate the
        closed loop) and ``feasible`` under the final policy
        (:func:`~hybridoc.workflows.policies.violation_summary` sums them up); empty for
        the simulator.
    """

    policy: torch.nn.Module
    losses: list[float] = field(default_factory=list)
    final_loss: float = float("nan")
    seconds: float = 0.0
    toi: str = "both"
    contact: str = "direct"
    integrator: str = "symplectic-euler"
    engine: str = "simulator"
    message: str = ""
    infeasible: int | None = None
    feasibility: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def feasible(self) -> bool | None:
        """Whether the final policy's closed loops meet every constraint on the training
        draws (``None``: not judged, the simulator's engine)."""
        return None if self.infeasible is None else self.infeasible == 0


def training_draws(
    problem: ProblemLike,
    samples: int,
    *,
    seed: int | None = None,
    distribution: Callable[[np.random.Generator, int], np.ndarray] | None = None,
) -> tuple[np.ndarray, int]:
    """Initial states to train on: the first ``samples`` draws of the problem's distribution.

    Parameters
    ----------
    problem
        A disc scene with a ``[distribution]`` table, or any problem with a Python
        distribution (:func:`~hybridoc.workflows.datasets.distribution_problem`).
    samples
        ``M >= 1``.
    seed
        Seed of the draws; default the distribution's seed plus one (a scene's, else 0),
        so that they are not the draws that
        :func:`~hybridoc.workflows.policies.validate_policy` judges by default.
    distribution
        A callable ``(rng, M) -> (M, nx)`` overriding the problem's distribution.

    Returns
    -------
    x0, seed
        ``(samples, nx)`` initial states and the seed they were drawn with.

    Raises
    ------
    SceneError
        No distribution, or one that cannot be drawn.
    """
    from hybridoc.problems import scene_of
    from hybridoc.resources import check_samples_of
    from hybridoc.workflows.datasets import (
        check_count,
        distribution_problem,
        draw_initial_states,
        source_seed,
    )

    samples = check_count(samples, "samples", 1)
    source = distribution_problem(problem, distribution)
    check_samples_of(source, samples)  # before drawing: the draws alone can exhaust memory
    seed = source_seed(source, None) + 1 if seed is None else check_count(seed, "seed", 0)
    table = scene_of(source, compiled=False)  # draws from a scene's [distribution] table
    if table is not None:
        dist = table.distribution
        x0 = np.stack([dist.draw(table, i, seed).initial_state() for i in range(samples)])
    else:
        x0 = draw_initial_states(source, samples, seed)
    return x0, seed


def train_policy(
    scene: ProblemLike,
    policy: torch.nn.Module,
    x0_batch: Any,
    *,
    toi: str = "both",
    iters: int = 100,
    lr: float = 1e-2,
    optimizer: str = "adam",
    contact: str = "direct",
    integrator: str = "symplectic-euler",
    seed: int = 0,
    schedule: str = "constant",
    keep_best: bool = True,
    callback: Callable[[int, float], None] | None = None,
    progress: ProgressLike = None,
    distribution: Callable[[np.random.Generator, int], np.ndarray] | None = None,
) -> TrainResult:
    """Train a feedback policy on the mean closed-loop cost over initial states.

    Full-batch Adam or L-BFGS on the mean over ``x0_batch`` of the closed-loop cost with
    zero-order hold. On a disc scene the cost is the differentiable simulator's discrete
    objective (terminal cost plus running cost,
    :meth:`~hybridoc.solvers.simulator.Simulator.policy_loss`); on any other problem it is
    the judge's event-exact cost, differentiated by its exact discrete adjoint
    (:func:`judged_loss`).

    Parameters
    ----------
    scene
        The problem: a disc scene (its grid, costs and contact parameters; its initial
        state is not used) or anything :func:`~hybridoc.problem.as_ocp` accepts.
    policy
        A batched ``torch.nn.Module`` ``(t (B,), s (B, nx)) -> u (B, nu)`` in float64, e.g.
        :func:`mlp_policy` (the judge also calls it with one state). Trained in place.
    x0_batch
        ``(B, nx)`` initial states, or a count ``M``: the first ``M``
        :func:`training_draws` of the problem's distribution (default seed).
    toi
        Time-of-impact correction of the simulator: ``"both"`` (the paper's method),
        ``"none"``, ``"position"`` or ``"velocity"``. The judge's gradient always has the
        event times' sensitivity: on a problem that is not a disc scene only ``"both"``.
    iters
        Optimiser iterations (L-BFGS: outer steps of at most 20 evaluations each).
    lr
        Learning rate.
    optimizer
        ``"adam"`` or ``"lbfgs"``.
    contact, integrator
        Contact model and integrator of the :class:`~hybridoc.solvers.simulator.Simulator`
        (disc scenes only).
    seed
        Seeds torch's global generator before training (for policies with randomness).
    schedule
        Adam's learning rate: ``"constant"`` or ``"cosine"`` (from ``lr`` down to
        ``lr / 100`` over the iterations).
    keep_best
        Adam: end with the parameters of the lowest loss seen (the loss is not monotone
        with a constant step), not those of the last update.
    callback
        Called as ``callback(iteration, loss)`` after each iteration.
    progress
        ``None``/``False`` (silent, the default), ``True`` (a progress bar on stderr) or a
        :class:`~hybridoc.progress.Progress`: the training stage and its iterations, with
        the loss.
    distribution
        For ``x0_batch`` a count: overrides the problem's distribution.

    Returns
    -------
    TrainResult

    Raises
    ------
    ControlsError
        Bad ``x0_batch`` or a policy that returns a wrong shape or non-finite value.
    SceneError
        An unknown optimiser or simulator setting, a simulator setting on a problem that is
        not a disc scene, no distribution to draw a count of initial states from.
    """
    params = _trainable(policy, optimizer, schedule, iters, lr)
    if isinstance(x0_batch, int | np.integer) and not isinstance(x0_batch, bool):
        x0_batch = training_draws(scene, int(x0_batch), distribution=distribution)[0]
    if _is_disc(scene):
        sim = Simulator(scene, contact=contact, toi=toi, integrator=integrator)
        x0 = _x0_tensor(x0_batch, sim.nx, batch_only=True)
        result = TrainResult(policy, toi=toi, contact=sim.contact, integrator=integrator)

        def loss() -> torch.Tensor:
            return sim.policy_loss(policy, x0)

    else:
        ocp = as_ocp(scene)
        _judge_settings(ocp, toi, contact, integrator)
        x0 = _x0_tensor(x0_batch, ocp.nx, batch_only=True)
        result = TrainResult(
            policy, toi="both", contact="exact", integrator="judge", engine="judge"
        )

        def loss() -> torch.Tensor:
            return judged_loss(ocp, policy, x0, params=params)

    torch.manual_seed(int(seed))
    t_start = time.perf_counter()
    with progress_scope(progress, "training") as p:
        p.stage(f"{optimizer} on {x0.shape[0]} initial states")
        step = _Steps(result, int(iters), callback, p)
        if optimizer == "adam":
            _train_adam(loss, policy, params, lr, schedule, keep_best, step)
        else:
            _train_lbfgs(loss, policy, params, lr, step)
    if not math.isfinite(result.final_loss):
        with torch.no_grad():
            result.final_loss = float(loss())
    result.seconds = time.perf_counter() - t_start
    if result.engine == "judge":
        _judge_feasibility(result, ocp, x0)
    return result


def _judge_feasibility(result: TrainResult, ocp: HybridOCP, x0: torch.Tensor) -> None:
    """``result.infeasible`` and ``feasibility``: the final policy judged on each training
    draw (one more closed loop each, no adjoint)."""
    judge_policy = _numpy_twin(result.policy)
    rows = []
    for row in x0.detach().numpy():
        try:
            ev = evaluate(ocp.replace(x0=row.copy()), policy=judge_policy, hold="zoh")
        except EvaluationError:  # not judged: counted in neither
            rows.append((np.nan, np.nan, np.nan, False))
        else:
            rows.append((ev.bound_violation, ev.path_violation, ev.terminal_violation,
                         ev.feasible))  # fmt: skip
    names = ("bound_violation", "path_violation", "terminal_violation", "feasible")
    cols = {k: np.array(v, dtype=bool if k == "feasible" else float)
            for k, v in zip(names, zip(*rows, strict=True), strict=True)}  # fmt: skip
    result.feasibility = cols
    result.infeasible = int(np.sum(~np.isnan(cols["bound_violation"]) & ~cols["feasible"]))


def _judge_settings(ocp: HybridOCP, toi: str, contact: str, integrator: str) -> None:
    """Refuse the simulator's settings on a problem that the judge trains."""
    if toi != "both":
        raise SceneError(
            f"toi={toi!r} needs a disc scene (the differentiable simulator's model); "
            f"{ocp.name!r} is trained through the judge's event-exact closed loop, whose "
            "exact adjoint always has the event times' sensitivity (toi='both')"
        )
    if contact != "direct" or integrator != "symplectic-euler":
        raise SceneError(
            f"contact and integrator are the disc simulator's settings; {ocp.name!r} is "
            "trained through the judge's event-exact closed loop"
        )


def _trainable(
    policy: torch.nn.Module, optimizer: str, schedule: str, iters: int, lr: float
) -> list[torch.Tensor]:
    """The policy's parameters to train, after the checks of :func:`train_policy`'s
    arguments."""
    if optimizer not in OPTIMIZERS:
        raise SceneError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    if schedule not in ("constant", "cosine"):
        raise SceneError(f"unknown schedule {schedule!r}; choose 'constant' or 'cosine'")
    if int(iters) < 0:
        raise SceneError(f"iters must be >= 0, got {iters}")
    if not lr >= 0 or not math.isfinite(lr):
        raise SceneError(f"lr must be a finite number >= 0, got {lr}")
    if not isinstance(policy, torch.nn.Module):
        raise ControlsError(f"policy must be a torch.nn.Module, got {type(policy).__name__}")
    params = [p for p in policy.parameters() if p.requires_grad]
    if not params:
        raise ControlsError("the policy has no parameters that require grad: nothing to train")
    return params
