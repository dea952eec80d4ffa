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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, EvaluationError, SceneError
from hybridoc.evaluator import adjoint, evaluate
from hybridoc.ocp import HybridOCP, as_float_array
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solvers.optimizers import LBFGS, lbfgs_torch_step
from hybridoc.solvers.simulator import Simulator
from hybridoc.solvers.threads import torch_threads

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


# ---------------------------------------------------------------------------- the policy
class MLPPolicy(torch.nn.Module):
    """A multilayer perceptron feedback policy ``u = pi(t, s)`` with fixed normalisations.

    ``pi(t, s) = u_offset + u_scale * net([2 t / T - 1, (s - s_mean) / s_scale])`` with
    ``net`` a ``tanh`` MLP, clipped to ``[u_min, u_max]`` when they are given (the
    ``saturation`` of the policy format, :mod:`hybridoc.workflows.policy_format`). Called
    with ``t`` of shape ``()`` or ``(B,)`` and ``s`` of shape ``(nx,)`` or ``(B, nx)``;
    returns ``(nu,)`` or ``(B, nu)``, so the same module runs in the judge (one state at a
    time) and in the simulator (a batch). Rows of a batch are independent.

    Parameters
    ----------
    nx, nu
        State and control dimensions.
    hidden
        Width of each hidden layer.
    layers
        Number of hidden layers.
    horizon
        ``T``, for the time input.
    s_mean, s_scale
        ``(nx,)`` state offset and scale of the input normalisation.
    u_offset, u_scale
        ``(nu,)`` output offset and scale.
    u_min, u_max
        ``(nu,)`` bounds the output is clipped to (``-inf``/``inf``: a side without one);
        ``None`` (default): no saturation. Where a control is clipped its gradient is zero,
        the exact gradient of the clipped policy.
    generator
        Random generator of the initial weights.
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        *,
        hidden: int,
        layers: int,
        horizon: float,
        s_mean: np.ndarray,
        s_scale: np.ndarray,
        u_offset: np.ndarray,
        u_scale: np.ndarray,
        u_min: np.ndarray | None = None,
        u_max: np.ndarray | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.nx, self.nu, self.horizon = int(nx), int(nu), float(horizon)
        f64 = torch.float64
        self.register_buffer("s_mean", torch.as_tensor(np.asarray(s_mean, float), dtype=f64))
        self.register_buffer("s_scale", torch.as_tensor(np.asarray(s_scale, float), dtype=f64))
        self.register_buffer("u_offset", torch.as_tensor(np.asarray(u_offset, float), dtype=f64))
        self.register_buffer("u_scale", torch.as_tensor(np.asarray(u_scale, float), dtype=f64))
        lo, hi = _output_bounds(u_min, u_max, self.nu)
        # None buffers: no saturation, and nothing in the state dict
        self.register_buffer("u_min", None if lo is None else torch.as_tensor(lo, dtype=f64))
        self.register_buffer("u_max", None if hi is None else torch.as_tensor(hi, dtype=f64))
        mods: list[torch.nn.Module] = []
        width = nx + 1
        for _ in range(layers):
            mods += [torch.nn.Linear(width, hidden, dtype=f64), torch.nn.Tanh()]
            width = hidden
        last = torch.nn.Linear(width, nu, dtype=f64)
        mods.append(last)
        self.net = torch.nn.Sequential(*mods)
        with torch.no_grad():
            for m in self.net:
                if isinstance(m, torch.nn.Linear):
                    bound = 1.0 / math.sqrt(m.in_features)
                    m.weight.copy_(
                        (torch.rand(m.weight.shape, generator=generator, dtype=f64) * 2 - 1) * bound
                    )
                    m.bias.zero_()
            # a small last layer: the untrained policy is close to the offset
            last.weight.mul_(0.1)

    def forward(self, t: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """The controls ``(nu,)`` for one state ``(nx,)``, or ``(B, nu)`` for ``(B, nx)``."""
        single = state.ndim == 1
        s = state.reshape(-1, self.nx).to(torch.float64)
        tt = torch.as_tensor(t, dtype=torch.float64).reshape(-1)
        tt = tt.expand(s.shape[0]) if tt.numel() == 1 else tt
        z = torch.cat(
            [(2.0 * tt / self.horizon - 1.0)[:, None], (s - self.s_mean) / self.s_scale], 1
        )
        u = self.u_offset + self.u_scale * self.net(z)
        if self.u_min is not None:
            u = torch.clamp(u, min=self.u_min, max=self.u_max)
        return u[0] if single else u


def _output_bounds(u_min: Any, u_max: Any, nu: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """:class:`MLPPolicy`'s clip bounds as ``(nu,)`` arrays (a missing side infinite), or
    ``(None, None)`` for none; the policy file checks them again when it is written
    (this module imports nothing of the policy format: the format imports it)."""
    if u_min is None and u_max is None:
        return None, None
    out = []
    for value, name, side in ((u_min, "u_min", -np.inf), (u_max, "u_max", np.inf)):
        arr = np.full(nu, side) if value is None else np.asarray(value, dtype=float).ravel()
        if arr.shape != (nu,) or np.isnan(arr).any():
            raise SceneError(f"MLPPolicy: {name} must be {nu} numbers (no NaN), got {value!r}")
        out.append(arr)
    if np.any(out[0] > out[1]):
        raise SceneError(f"MLPPolicy: u_min {out[0]} exceeds u_max {out[1]}")
    return out[0], out[1]


def mlp_policy(
    scene: ProblemLike,
    *,
    hidden: int = 32,
    layers: int = 2,
    seed: int = 0,
    distribution: Callable[[np.random.Generator, int], np.ndarray] | None = None,
    saturate: bool = True,
) -> MLPPolicy:
    """A small MLP feedback policy that starts near the problem's initial guess.

    The time input is normalised to ``[-1, 1]`` and the output is ``u_offset + u_scale``
    times the network, whose last layer starts small. The other scales depend on the
    problem:

    A disc scene
        Positions relative to the initial state by the scene's length scale (the spread of
        the initial positions and targets, at least 1), velocities by the velocity the
        initial control reaches over the horizon (at least 1); ``u_offset`` is the scene's
        initial control (its mean over the grid), ``u_scale`` its largest magnitude (at
        least 1).
    Any other :class:`~hybridoc.HybridOCP`
        ``s_mean`` is the mean of 64 draws of its distribution (``distribution``, else the
        problem's; none: ``x0``) and ``s_scale`` per state the larger of their standard
        deviation and half the range the state covers under the initial guess ``u_guess``
        from ``s_mean`` (1 for a state that moves in neither). ``u_offset`` is the mean of
        ``u_guess``; ``u_scale`` per control is half the bound interval where both bounds
        are finite, else the control that moves the state it drives fastest by its scale
        over the horizon, ``min_i s_scale_i / (T |df_i/du_j|)`` at ``(s_mean, u_offset)``
        (1 for a control that drives no state there). On a problem with control bounds
        the output is clipped to them (``saturate``), so that no policy trained from it
        leaves them (the judge's :attr:`Evaluation.bound_violation <hybridoc.Evaluation>`
        is 0); the clip is part of the saved policy file (its ``saturation``).

    Parameters
    ----------
    scene
        A problem: a disc scene (a :class:`~hybridoc.problems.Scene`, built-in name or TOML
        path) or anything :func:`~hybridoc.problem.as_ocp` accepts.
    hidden
        Width of each hidden layer.
    layers
        Number of hidden layers.
    seed
        Seed of the initial weights (the result is deterministic).
    distribution
        A callable ``(rng, M) -> (M, nx)`` of initial states for a problem that is not a
        disc scene (:attr:`HybridOCP.distribution <hybridoc.HybridOCP>`); default the
        problem's own. Not used on a disc scene.
    saturate
        Clip the output to the problem's control bounds (where it has any). ``False``:
        an unclipped policy, whose controls the judge may find out of bounds.

    Returns
    -------
    MLPPolicy
        A float64 ``torch.nn.Module``.

    Raises
    ------
    SceneError
        Bad ``hidden`` or ``layers``, a distribution that cannot be drawn.
    """
    if hidden < 1 or layers < 0:
        raise SceneError(f"hidden must be >= 1 and layers >= 0, got {hidden}, {layers}")
    gen = torch.Generator().manual_seed(int(seed))
    ocp = as_ocp(scene)
    if ocp.capabilities.geometry is not None:
        return _disc_mlp(ocp, int(hidden), int(layers), gen)
    s_mean, s_scale, u_offset, u_scale = _generic_scales(ocp, distribution)
    clip = saturate and ocp.has_bounds
    return MLPPolicy(
        ocp.nx, ocp.nu, hidden=int(hidden), layers=int(layers), horizon=ocp.horizon,
        s_mean=s_mean, s_scale=s_scale, u_offset=u_offset, u_scale=u_scale,
        u_min=ocp.u_min if clip else None, u_max=ocp.u_max if clip else None, generator=gen,
    )  # fmt: skip


def _is_disc(problem: ProblemLike) -> bool:
    """Whether ``problem`` is a disc scene (the differentiable simulator's model)."""
    from hybridoc.problems import load_problem, scene_of

    obj = load_problem(problem) if isinstance(problem, str | Path) else problem
    return scene_of(obj) is not None


def _disc_mlp(ocp: HybridOCP, hidden: int, layers: int, gen: torch.Generator) -> MLPPolicy:
    """:func:`mlp_policy` of bodies in the plane (its docstring: "A disc scene"), from the
    problem's geometry (:attr:`Capabilities.geometry
    <hybridoc.capabilities.Capabilities.geometry>`) and data."""
    geometry = ocp.capabilities.geometry
    assert geometry is not None
    x0 = np.array(ocp.x0, dtype=float)
    n = geometry.n_bodies
    pts = [tuple(geometry.position(x0, i)) for i in range(n)]
    pts += [b.target for b in geometry.bodies if b.target is not None]
    pts_a = np.array(pts, dtype=float)
    length = max(1.0, float(np.max(pts_a.max(0) - pts_a.min(0))))
    u0 = np.array(ocp.u_guess, dtype=float)
    u_mag = float(np.max(np.abs(u0))) if u0.size else 0.0
    m_min = min(b.mass for b in geometry.bodies)
    speed = max(1.0, u_mag * ocp.horizon / m_min)
    s_scale = np.r_[np.full(2 * n, length), np.full(2 * n, speed)]
    return MLPPolicy(
        4 * n,
        ocp.nu,
        hidden=hidden,
        layers=layers,
        horizon=ocp.horizon,
        s_mean=x0,
        s_scale=s_scale,
        u_offset=u0.mean(0),
        u_scale=np.full(ocp.nu, max(1.0, u_mag)),
        generator=gen,
    )


SCALE_DRAWS = 64
"""Draws of the distribution that :func:`mlp_policy` averages on a problem that is not a
disc scene."""


def _generic_scales(
    problem: ProblemLike,
    distribution: Callable[[np.random.Generator, int], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The normalisations of :func:`mlp_policy` for a problem that is not a disc scene.

    Parameters
    ----------
    problem
        Anything :func:`~hybridoc.problem.as_ocp` accepts.
    distribution
        Overrides the problem's distribution; with neither, the states are ``x0``.

    Returns
    -------
    s_mean, s_scale, u_offset, u_scale
        ``(nx,)``, ``(nx,)``, ``(nu,)``, ``(nu,)`` (:func:`mlp_policy`, "Any other
        HybridOCP"); every scale positive.
    """
    import casadi as ca

    from hybridoc.workflows.datasets import draw_initial_states

    ocp = as_ocp(problem)
    dist = distribution if distribution is not None else ocp.distribution
    if dist is None:
        draws = ocp.x0[None, :]
    else:
        draws = draw_initial_states(ocp.replace(distribution=dist), SCALE_DRAWS, 0)
    s_mean = draws.mean(0)
    spread = draws.std(0)
    u_offset = np.asarray(ocp.u_guess, dtype=float).mean(0)
    reach = np.zeros(ocp.nx)
    try:
        ev = evaluate(ocp.replace(x0=s_mean, distribution=None), ocp.u_guess)
        visited = np.array([seg.s0 for seg in ev.segments] + [ev.final_state])
        reach = 0.5 * (visited.max(0) - visited.min(0))
    except (EvaluationError, ControlsError):
        pass  # the initial guess cannot be judged from s_mean: the draws' spread alone
    s_scale = np.maximum(spread, reach)
    s_scale = np.where(s_scale > 1e-12 * (1.0 + np.abs(s_mean)), s_scale, 1.0)
    s, u = ca.MX.sym("s", ocp.nx), ca.MX.sym("u", ocp.nu)
    B = np.array(ca.Function("B", [s, u], [ca.jacobian(ocp.f(s, u), u)])(s_mean, u_offset))
    B = B.reshape(ocp.nx, ocp.nu)
    u_scale = np.ones(ocp.nu)
    for j in range(ocp.nu):
        lo, hi = float(ocp.u_min[j]), float(ocp.u_max[j])
        if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
            u_scale[j] = 0.5 * (hi - lo)
            continue
        drive = np.abs(B[:, j])
        driven = drive > 1e-12 * max(1.0, float(drive.max(initial=0.0)))
        if driven.any():
            u_scale[j] = float(np.min(s_scale[driven] / (ocp.horizon * drive[driven])))
    return s_mean, s_scale, u_offset, u_scale


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


@dataclass
class _Steps:
    """Where each iteration's loss goes: the result, the callback and the progress."""

    result: TrainResult
    iters: int
    callback: Callable[[int, float], None] | None
    progress: Progress

    def __call__(self, it: int, value: float) -> None:
        self.result.losses.append(value)
        if self.callback is not None:
            self.callback(it, value)
        self.progress.count(it + 1, self.iters, f"loss {value:.6g}")

    def stop(self, it: int, exc: EvaluationError) -> None:
        """Record why the training ends at iteration ``it``."""
        self.result.message = (
            f"stopped at iteration {it + 1} of {self.iters}: the judge could not simulate a "
            f"closed loop ({exc}); the policy has the best parameters judged"
        )
        self.progress.detail(self.result.message)


def _snapshot(policy: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in policy.state_dict().items()}


def _train_adam(
    loss_fn: Callable[[], torch.Tensor],
    policy: torch.nn.Module,
    params: list[torch.Tensor],
    lr: float,
    schedule: str,
    keep_best: bool,
    step: _Steps,
) -> None:
    """Full-batch Adam (:func:`train_policy`), ending with the best parameters seen when
    ``keep_best`` (or when the judge fails on an update: then training stops)."""
    opt = TensorAdam(params, lr)
    lrs = (
        cosine_annealing_lrs(lr, lr / 100, max(step.iters, 1), step.iters)
        if schedule == "cosine"
        else None
    )
    best, best_state = math.inf, None
    for it in range(step.iters):
        opt.zero_grad()
        try:
            loss = loss_fn()
        except EvaluationError as exc:
            step.stop(it, exc)
            break
        loss.backward()
        value = float(loss.detach())
        if (keep_best or step.result.engine == "judge") and value < best:
            best = value
            best_state = _snapshot(policy)
        opt.step()
        if lrs is not None:
            opt.lr = lrs[it + 1]
        step(it, value)
    if best_state is None:
        return
    last = math.inf
    if not step.result.message:
        try:
            with torch.no_grad():
                last = float(loss_fn())
        except EvaluationError:
            pass  # the last update cannot be judged: the best parameters seen
    if keep_best and best < last or not math.isfinite(last):
        policy.load_state_dict(best_state)
        step.result.final_loss = best
    else:
        step.result.final_loss = last


def _train_lbfgs(
    loss_fn: Callable[[], torch.Tensor],
    policy: torch.nn.Module,
    params: list[torch.Tensor],
    lr: float,
    step: _Steps,
) -> None:
    """Full-batch L-BFGS with a strong Wolfe line search (:func:`train_policy`); a step the
    judge cannot simulate ends the training with the parameters before it.

    Each iteration is one call of ``torch.optim.LBFGS(max_iter=20,
    line_search_fn="strong_wolfe")`` with torch's defaults, by its numpy port
    (:func:`~hybridoc.solvers.optimizers.lbfgs_torch_step`) on the flattened parameters.
    torch's call first evaluates the loss where the previous call ended, which that call's
    line search has just done: the loss is deterministic, so its value and gradient are
    reused (one closed loop of the batch less per iteration, and at the end)."""
    opt = LBFGS(lr, history_size=100, tolerance_grad=1e-7, tolerance_change=1e-9)
    flat = _FlatParameters(params)

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        flat.set(x)
        for p in params:
            p.grad = None
        loss = loss_fn()
        loss.backward()
        return float(loss.detach()), flat.grad()

    x = flat.get()
    start: tuple[float, np.ndarray] | None = None  # the loss and gradient at x
    for it in range(step.iters):
        before = _snapshot(policy)
        try:
            if start is None:
                start = fun(x)
            f, g = start
            x_new, f_new, g_new = lbfgs_torch_step(opt, fun, x, f, g, max_iter=20)
        except EvaluationError as exc:
            policy.load_state_dict(before)
            step.stop(it, exc)
            break
        x, start = x_new, (f_new, g_new)
        flat.set(x)
        step(it, f)
    if start is not None:
        step.result.final_loss = start[0]


class _FlatParameters:
    """Tensors as one flat numpy vector (their common dtype) and back: L-BFGS's iterate."""

    def __init__(self, params: list[torch.Tensor]) -> None:
        self.params = params

    def get(self) -> np.ndarray:
        return np.concatenate([p.detach().cpu().numpy().ravel() for p in self.params])

    def grad(self) -> np.ndarray:
        # no gradient (a parameter the loss does not use): zeros, as torch.optim.LBFGS
        return np.concatenate([
            torch.zeros(p.numel(), dtype=p.dtype).numpy() if p.grad is None
            else p.grad.detach().cpu().numpy().ravel()
            for p in self.params
        ])  # fmt: skip

    def set(self, x: np.ndarray) -> None:
        offset = 0
        with torch.no_grad():
            for p in self.params:
                n = p.numel()
                p.copy_(torch.as_tensor(x[offset : offset + n]).view_as(p))
                offset += n


class TensorAdam:
    """Adam on torch tensors in place: ``torch.optim.Adam``'s step, without ``torch.optim``.

    The arithmetic of torch's single-tensor Adam (its CPU path) with its defaults: no
    weight decay, no AMSGrad, ``maximize=False``. Per tensor, at its ``k``-th step,
    ``m.lerp_(g, 1 - beta1)``, ``v.mul_(beta2).addcmul_(g, g, value=1 - beta2)``, then
    ``p.addcdiv_(m, v.sqrt() / sqrt(1 - beta2^k) + eps, value=-lr / (1 - beta1^k))``;
    a tensor without a gradient is skipped (and its ``k`` does not advance), so the
    iterates are those of ``torch.optim.Adam`` bit for bit on the CPU, in float64 and
    float32. Building a ``torch.optim`` optimiser imports ``torch._dynamo`` the first time
    (seconds per process); this does not.

    Parameters
    ----------
    params
        The tensors to train (leaves that require grad).
    lr
        The learning rate; the attribute ``lr`` may be changed between steps (a schedule).
    betas
        The decay rates of the gradient's first and second moment averages.
    eps
        Added to the denominator.

    Raises
    ------
    SceneError
        ``lr`` negative or not finite, or ``betas`` outside ``[0, 1)``.
    """

    def __init__(
        self,
        params: Sequence[torch.Tensor],
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        if not lr >= 0 or not math.isfinite(lr):
            raise SceneError(f"lr must be a finite number >= 0, got {lr}")
        if not all(0.0 <= b < 1.0 for b in betas):
            raise SceneError(f"betas must be in [0, 1), got {betas}")
        self.params = list(params)
        self.lr = lr
        self.betas = betas
        self.eps = eps
        self.steps = [0] * len(self.params)
        self.moments: list[tuple[torch.Tensor, torch.Tensor] | None] = [None] * len(self.params)

    def zero_grad(self) -> None:
        """Forget the gradients (``None``, as ``torch.optim``'s ``zero_grad``)."""
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        """One Adam step of every tensor that has a gradient."""
        beta1, beta2 = self.betas
        with torch.no_grad():
            for i, p in enumerate(self.params):
                grad = p.grad
                if grad is None:
                    continue
                if self.moments[i] is None:
                    zeros = torch.zeros_like(p, memory_format=torch.preserve_format)
                    self.moments[i] = (zeros, zeros.clone())
                exp_avg, exp_avg_sq = self.moments[i]  # type: ignore[misc]
                self.steps[i] += 1
                # torch counts steps in a float tensor and raises the betas to its value
                k = float(self.steps[i])
                exp_avg.lerp_(grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                step_size = self.lr / (1 - beta1**k)
                bias_correction2_sqrt = (1 - beta2**k) ** 0.5
                denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
                p.addcdiv_(exp_avg, denom, value=-step_size)


def cosine_annealing_lrs(base_lr: float, eta_min: float, t_max: int, steps: int) -> list[float]:
    """The learning rates of ``torch.optim.lr_scheduler.CosineAnnealingLR``, step by step.

    Its recursive form (what its ``step()`` computes from the previous rate), so that the
    rates are torch's bit for bit; they follow
    ``eta_min + (base_lr - eta_min) (1 + cos(pi k / t_max)) / 2`` up to rounding.

    Parameters
    ----------
    base_lr
        The rate before the first step.
    eta_min
        The lowest rate.
    t_max
        The steps from ``base_lr`` down to ``eta_min`` (``>= 1``).
    steps
        How many scheduler steps.

    Returns
    -------
    list of float
        ``steps + 1`` rates: ``[0]`` is ``base_lr``, ``[k]`` the rate after ``k`` steps.

    Raises
    ------
    SceneError
        ``t_max < 1``.
    """
    if t_max < 1:
        raise SceneError(f"t_max must be >= 1, got {t_max}")
    lrs = [base_lr]
    lr = base_lr
    for k in range(1, steps + 1):
        if (k - 1 - t_max) % (2 * t_max) == 0:
            # torch's restart branch: past the minimum the rate climbs back
            lr = lr + (base_lr - eta_min) * (1 - math.cos(math.pi / t_max)) / 2
        else:
            # torch's order of operations: (ratio * (lr - eta_min)) + eta_min
            ratio = (1 + math.cos(math.pi * k / t_max)) / (1 + math.cos(math.pi * (k - 1) / t_max))
            lr = ratio * (lr - eta_min) + eta_min
        lrs.append(lr)
    return lrs


def judged_loss(
    problem: ProblemLike,
    policy: torch.nn.Module,
    x0: Any,
    *,
    params: Sequence[torch.Tensor] | None = None,
) -> torch.Tensor:
    """What :func:`train_policy` minimises on a problem that is not a disc scene.

    The mean over ``x0`` of the judge's closed-loop cost (zero-order hold) as a
    differentiable torch scalar, as :func:`closed_loop_cost`, except that the judge rolls
    out a numpy copy of an :class:`MLPPolicy` (the function its saved policy file computes,
    the same to rounding, ten times faster to call per grid step than the module); the
    backward pass differentiates the module along that closed loop by the exact discrete
    adjoint, event times included (module notes).

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    policy
        A batched torch policy (:func:`closed_loop_cost`), e.g. :func:`mlp_policy`.
    x0
        ``(nx,)`` or ``(B, nx)`` initial states.
    params
        The tensors to differentiate with respect to; default the policy's parameters that
        require grad.

    Returns
    -------
    torch.Tensor
        A float64 scalar; ``.backward()`` fills the parameters' ``.grad``.

    Raises
    ------
    ControlsError, EvaluationError
        As :func:`closed_loop_cost`.
    """
    torch_threads()
    ocp = as_ocp(problem)
    x = _x0_tensor(x0, ocp.nx)
    if params is None:
        params = [p for p in policy.parameters() if p.requires_grad]
    runner = _Runner(ocp, policy, {}, judge_policy=_numpy_twin(policy))
    return _ClosedLoopCost.apply(runner, x, *params)


def _numpy_twin(policy: torch.nn.Module) -> Callable[..., Any]:
    """What the judge rolls out for ``policy``: for an :class:`MLPPolicy`, the same function
    in numpy (as the saved policy file computes it; a torch call per grid step costs ten
    times more than the judge's step), otherwise the policy itself."""
    if not isinstance(policy, MLPPolicy):
        return policy
    layers = [m for m in policy.net if isinstance(m, torch.nn.Linear)]
    if len(layers) + sum(isinstance(m, torch.nn.Tanh) for m in policy.net) != len(policy.net):
        return policy

    def arr(x: torch.Tensor) -> np.ndarray:
        return x.detach().cpu().numpy().astype(float).copy()

    Ws = [arr(m.weight) for m in layers]
    bs = [arr(m.bias) for m in layers]
    mean, scale = arr(policy.s_mean), arr(policy.s_scale)
    off, gain = arr(policy.u_offset), arr(policy.u_scale)
    lo = None if policy.u_min is None else arr(policy.u_min)
    hi = None if policy.u_max is None else arr(policy.u_max)
    horizon = policy.horizon

    def numpy_policy(t: float, state: np.ndarray) -> np.ndarray:
        z = np.concatenate([[2.0 * float(t) / horizon - 1.0], (state - mean) / scale])
        for k, (W, b) in enumerate(zip(Ws, bs, strict=True)):
            z = W @ z + b
            if k < len(Ws) - 1:
                z = np.tanh(z)
        u = off + gain * z
        # the same clip as MLPPolicy.forward and the policy file's (exact: max, min)
        return u if lo is None else np.minimum(np.maximum(u, lo), hi)

    return numpy_policy


def _x0_tensor(x0: Any, nx: int, *, batch_only: bool = False) -> torch.Tensor:
    """``x0`` as a float64 ``(B, nx)`` tensor, or one clear ControlsError."""
    if isinstance(x0, torch.Tensor):
        x = x0.to(torch.float64)
        if x.is_complex():
            raise ControlsError("x0 must be real numbers")
    else:
        x = torch.as_tensor(as_float_array(x0, "x0", error=ControlsError))
    ok = x.ndim == 2 if batch_only else x.ndim in (1, 2)
    if not ok or x.shape[-1] != nx or x.numel() == 0:
        want = f"(B, {nx})" if batch_only else f"({nx},) or (B, {nx})"
        raise ControlsError(f"x0 must have shape {want}, got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ControlsError("x0 contains NaN or infinite values")
    return x.reshape(-1, nx)


# ---------------------------------------------------------------------------- exact gradient
@dataclass
class ClosedLoopGradient:
    """The judge's closed-loop evaluation of one initial state and its adjoint quantities.

    Attributes
    ----------
    cost
        The judge's cost ``J``.
    d_controls
        ``(N, nu)``: ``g_n``, the derivative of ``J`` with respect to ``u_n`` alone, the
        policy's reaction in later intervals included.
    d_initial_state
        ``(nx,)``: ``dJ/ds(0)`` of the closed loop.
    grid_states
        ``(N, nx)``: the states ``s(t_n)`` at which the policy was called.
    feedback
        ``(N, nu, nx)``: the policy's state Jacobians there.
    evaluation
        The judge's :class:`~hybridoc.evaluation.Evaluation`.
    """

    cost: float
    d_controls: np.ndarray
    d_initial_state: np.ndarray
    grid_states: np.ndarray
    feedback: np.ndarray
    evaluation: Any


def _policy_batch(
    policy: Callable[..., Any], t: torch.Tensor, s: torch.Tensor, nu: int
) -> torch.Tensor:
    try:
        out = policy(t, s)
    except Exception as exc:
        raise ControlsError(
            f"the policy raised {type(exc).__name__} on a batch of {s.shape[0]} states "
            f"(closed_loop_cost calls it batched: t (B,), state (B, nx)): {exc}"
        ) from exc
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (s.shape[0], nu):
        shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ControlsError(
            f"the policy returned {shape} for a batch of {s.shape[0]} states; expected "
            f"({s.shape[0]}, {nu}): closed_loop_cost needs a batched torch policy"
        )
    if not bool(torch.isfinite(out).all()):
        raise ControlsError("the policy returned a non-finite control")
    return out


def closed_loop_gradient(
    problem: ProblemLike, policy: Callable[..., Any], x0: Any = None, **kwargs: Any
) -> ClosedLoopGradient:
    """The judge's zero-order-hold closed-loop evaluation and its exact adjoint.

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    policy
        A batched torch policy ``(t (B,), s (B, nx)) -> (B, nu)`` that also accepts one
        state (``t`` of shape ``()``, ``s`` of shape ``(nx,)``), e.g. :func:`mlp_policy`.
    x0
        ``(nx,)`` initial state; default the problem's.
    **kwargs
        Passed to :func:`hybridoc.evaluate` (``graze_tol``, ...).

    Returns
    -------
    ClosedLoopGradient
    """
    return _closed_loop(as_ocp(problem), policy, policy, x0, kwargs)


def _closed_loop(
    ocp: HybridOCP,
    policy: Callable[..., Any],
    judge_policy: Callable[..., Any],
    x0: Any,
    kwargs: dict[str, Any],
) -> ClosedLoopGradient:
    """:func:`closed_loop_gradient` with ``judge_policy`` rolled out (the same function as
    ``policy``, which is differentiated)."""
    if x0 is not None:
        ocp = ocp.replace(x0=_x0_tensor(x0, ocp.nx)[0].detach().numpy().copy())
    ev = evaluate(ocp, policy=judge_policy, hold="zoh", **kwargs)
    idx = np.array([seg.interval for seg in ev.segments], dtype=int)
    first = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    S = np.array([ev.segments[i].s0 for i in first])
    assert S.shape == (ocp.steps, ocp.nx)
    J = _state_jacobians(policy, ocp, S)
    g = adjoint(ev, feedback=J)
    return ClosedLoopGradient(
        cost=ev.cost,
        d_controls=g.d_controls,
        d_initial_state=g.d_initial_state,
        grid_states=S,
        feedback=J,
        evaluation=ev,
    )


def _state_jacobians(policy: Callable[..., Any], ocp: HybridOCP, S: np.ndarray) -> np.ndarray:
    """``d pi/d s (t_n, s_n)``, ``(N, nu, nx)``, by ``nu`` backward passes of one batch."""
    t = torch.as_tensor(ocp.time_grid()[:-1], dtype=torch.float64)
    s = torch.as_tensor(S, dtype=torch.float64).requires_grad_(True)
    with torch.enable_grad():
        out = _policy_batch(policy, t, s, ocp.nu)
        if not out.requires_grad:  # the policy ignores the state
            return np.zeros((S.shape[0], ocp.nu, ocp.nx))
        rows = []
        for j in range(ocp.nu):
            (gj,) = torch.autograd.grad(
                out[:, j].sum(), s, retain_graph=j < ocp.nu - 1, allow_unused=True
            )
            rows.append(torch.zeros_like(s) if gj is None else gj)
    return torch.stack(rows, 1).detach().numpy()


class _ClosedLoopCost(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, runner: _Runner, x0: torch.Tensor, *params: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        results = [runner.one(row) for row in x0.detach()]
        ctx.runner = runner
        ctx.results = results
        ctx.n_params = len(params)
        ctx.save_for_backward(*params)
        cost = float(np.mean([r.cost for r in results]))
        return torch.tensor(cost, dtype=torch.float64)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[Any, ...]:  # type: ignore[override]
        runner: _Runner = ctx.runner
        results: list[ClosedLoopGradient] = ctx.results
        params = ctx.saved_tensors
        B = len(results)
        w = grad.to(torch.float64) / B
        d_x0 = torch.as_tensor(np.array([r.d_initial_state for r in results])) * w
        if not params:
            return (None, d_x0)
        ocp = runner.ocp
        t = torch.as_tensor(np.tile(ocp.time_grid()[:-1], B), dtype=torch.float64)
        s = torch.as_tensor(np.concatenate([r.grid_states for r in results]), dtype=torch.float64)
        g = torch.as_tensor(np.concatenate([r.d_controls for r in results])) * w
        with torch.enable_grad():
            out = _policy_batch(runner.policy, t, s, ocp.nu)
            if not out.requires_grad:  # no parameter acts on the output
                return (None, d_x0, *(torch.zeros_like(p) for p in params))
            grads = torch.autograd.grad(out, params, grad_outputs=g, allow_unused=True)
            grads = tuple(
                torch.zeros_like(p) if gr is None else gr
                for p, gr in zip(params, grads, strict=True)
            )
        return (None, d_x0, *grads)


class _Runner:
    """The closed loops of :class:`_ClosedLoopCost`: ``judge_policy`` (default ``policy``)
    is rolled out by the judge, ``policy`` differentiated."""

    def __init__(
        self,
        ocp: HybridOCP,
        policy: Callable[..., Any],
        kwargs: dict[str, Any],
        judge_policy: Callable[..., Any] | None = None,
    ) -> None:
        self.ocp, self.policy, self.kwargs = ocp, policy, kwargs
        self.judge_policy = policy if judge_policy is None else judge_policy

    def one(self, x0: torch.Tensor) -> ClosedLoopGradient:
        return _closed_loop(self.ocp, self.policy, self.judge_policy, x0, self.kwargs)


def closed_loop_cost(
    problem: ProblemLike,
    policy: torch.nn.Module | Callable[..., Any],
    x0: Any = None,
    *,
    params: Sequence[torch.Tensor] | None = None,
    **kwargs: Any,
) -> torch.Tensor:
    """The judge's closed-loop cost (zero-order hold) as a differentiable torch scalar.

    The value is the mean over the initial states of
    ``hybridoc.evaluate(problem with x0, policy=policy).cost``, the event-exact continuous
    cost. Its backward pass is the exact gradient (module notes) with respect to the
    policy's parameters, and to ``x0`` when that is a tensor that requires grad. It is the
    derivative of the judge's cost wherever the event sequence does not change under the
    perturbation.

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    policy
        A batched torch policy ``(t (B,), s (B, nx)) -> (B, nu)`` that also accepts a single
        state (``t`` of shape ``()``, ``s`` of shape ``(nx,)``), such as :func:`mlp_policy`;
        rows of a batch must be independent.
    x0
        ``(nx,)`` or ``(B, nx)`` initial states; default the problem's.
    params
        The tensors to differentiate with respect to; default the policy's parameters that
        require grad.
    **kwargs
        Passed to :func:`hybridoc.evaluate` (``graze_tol``, ``penetration_tol``, ...).

    Returns
    -------
    torch.Tensor
        A float64 scalar; ``.backward()`` fills the parameters' ``.grad``.

    Raises
    ------
    ControlsError
        A wrong ``x0``, or a policy that raises or returns a wrong shape or non-finite value.
    EvaluationError
        What the judge raises (sustained contact, Zeno behaviour, ...).
    """
    torch_threads()
    ocp = as_ocp(problem)
    if x0 is None:
        x = torch.as_tensor(ocp.x0, dtype=torch.float64)[None, :]
    else:
        x = _x0_tensor(x0, ocp.nx)
    if params is None:
        params = (
            [p for p in policy.parameters() if p.requires_grad]
            if isinstance(policy, torch.nn.Module)
            else []
        )
    return _ClosedLoopCost.apply(_Runner(ocp, policy, kwargs), x, *params)
