"""Feedback policies, the network (:mod:`hybridoc.workflows.training`): :class:`MLPPolicy`
and :func:`mlp_policy`, whose normalisation comes from the problem."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, EvaluationError, SceneError
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ProblemLike, as_ocp


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
