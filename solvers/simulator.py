"""A differentiable disc-and-wall simulator in torch with the paper's contact models.

:class:`Simulator` integrates a :class:`~hybridoc.problems.Scene` on its N-grid with symplectic
Euler and resolves contacts with one of several models. It is a ``torch.nn.Module``: the
rollout and the discrete objective are differentiable with respect to the controls, the
initial state and the scene parameters (radii, masses, restitution, targets).

The discrete step (Zhong et al. 2023, section 4; DESIGN.md section 3)
    With ``a_n = M^-1 B u_n`` the accelerations,

    .. math::

        \\hat v = v_n + a_n \\Delta t, \\qquad \\hat p = p_n + \\hat v \\Delta t .

    Contact ``c`` (a disc pair ``i < j`` or a disc and a wall) is *detected* when the
    penetrated state ends in penetration and approaches: gap ``d_c(\\hat p) < 0`` and normal
    speed ``\\hat w_c = J_c(\\hat p) \\hat v < 0``. Its time of impact (paper Eq. 3) is
    ``toi_c = d_c / \\hat w_c`` clipped to ``[0, \\Delta t]``: the collision happened
    ``\\Delta t - toi_c`` after the step start. The time-of-impact settings are

    ``none``
        the impulse is computed at the penetrated state (``\\hat p``, ``\\hat v``, normal
        ``\\hat n``) and ``p_{n+1} = \\hat p``.
    ``position`` (Hu et al. 2020)
        the same impulse; ``p_{n+1} = p_n + \\hat v (\\Delta t - toi) + v_{n+1} toi``.
    ``velocity`` (the paper's section 4.2 alone)
        the impulse is computed at the collision state (Eqs. 4-6)
        ``\\bar v = v_n + a_n (\\Delta t - toi)``, ``\\bar p = p_n + \\hat v (\\Delta t - toi)``,
        normal ``\\bar n`` from ``\\bar p``; ``p_{n+1} = \\hat p``.
    ``both`` (the paper's method, the default)
        the impulse of ``velocity`` and the position correction of ``position``.

    In every setting ``v_{n+1} = \\hat v + M^{-1} J^T \\lambda``: the velocity change of the
    impulse is added to the velocity at the end of the step, as in the paper's public
    implementation (so the force acts during the whole step).

Several contacts in one step
    All contacts detected in a step are resolved together. Each contact ``c`` keeps its own
    time of impact: its Jacobian row ``J_c`` (``+n`` on disc ``i``, ``-n`` on disc ``j``; the
    wall normal on the disc of a wall contact) and its pre-impact normal speed ``w_c`` are
    taken at its own collision state (or at the penetrated state for ``none``/``position``).
    The impulses ``lambda`` come from the chosen impulse solver on the Delassus matrix
    ``W = J M^-1 J^T`` of the detected contacts: ``direct`` treats each contact on its own,
    ``lambda_c = -(1 + e) w_c / W_cc`` for an approaching contact (the paper's and Taichi's
    treatment), ``lcp`` and ``convex`` (:mod:`hybridoc.solvers.contacts`) couple them. The
    position correction is per contact: ``p_{n+1} = \\hat p + sum_c toi_c M^-1 J_c^T
    \\lambda_c``. With one contact per step this is exactly the paper's method.

Exact integrator (an extension, not in the paper)
    ``integrator="exact"`` replaces symplectic Euler by the exact flow of the
    piecewise-constant force, ``p_hat = p_n + v_n dt + a_n dt^2 / 2``, and refines
    each detected contact's time of impact by Newton's method on its gap along that flow
    (started from the paper's Eq. 3). The impulse is then computed at the exact collision
    state and the position correction is the exact remaining flow, so with at most one event
    per contact and step the discrete loss *is* the continuous cost of the piecewise-constant
    control (to rounding) and its gradient is the exact one. Symplectic Euler's implied path
    has a kink at every grid point, which makes the discrete loss kink whenever a contact
    moves to another step; the exact flow has no such kinks.

Contact models
    The step itself belongs to the contact model (:mod:`hybridoc.solvers.contacts`): the
    impulse models ``direct``, ``lcp`` and ``convex`` share the time-of-impact logic above;
    ``compliant`` (penalty spring-damper) and ``pbd`` (position-based projection) are not
    impulse models. Gaps, normals, impulses and times of impact come from
    :mod:`hybridoc.problems.physics`, shared with the judge and the CasADi step.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, SceneError
from hybridoc.problem import disc_scene
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts import TOI_MODES, ContactModel, contact_model
from hybridoc.solvers.threads import torch_threads

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problem import ProblemLike

__all__ = ["Simulator", "TOI_MODES", "INTEGRATORS", "NEWTON_ITERATIONS", "disc_scene"]


INTEGRATORS = ("symplectic-euler", "exact")
NEWTON_ITERATIONS = 4
"""Newton iterations refining the time of impact of the exact integrator (quadratic
convergence from the linear estimate, whose error is O(a dt^2))."""


class Simulator(torch.nn.Module):
    """Differentiable disc simulator (symplectic Euler or the exact flow) with contact models.

    Parameters
    ----------
    scene : Scene, str or DiscOCP
        A disc problem: a :class:`~hybridoc.problems.Scene`, a built-in scene name, a TOML
        path, or the HybridOCP of a scene.
    contact : ContactModel or str
        The contact model: an instance (``LCP(toi="both")``, ``Compliant(stiffness=2e4)``)
        or a name of :data:`hybridoc.solvers.contacts.CONTACT_MODELS` (``"direct"`` by
        default, ``"lcp"``, ``"convex"``, ``"compliant"``, ``"pbd"``), also as
        ``"lcp/both"``; parsed once by :func:`~hybridoc.solvers.contacts.contact_model`.
    toi : str, optional
        Time-of-impact correction of an impulse model: ``"none"``, ``"position"``,
        ``"velocity"`` or ``"both"``; ``None`` (default) keeps the model's own (``"both"``,
        the paper's method, for a name). Ignored by the other models.
    integrator
        ``"symplectic-euler"`` (default, the paper's scheme) or ``"exact"``: the exact flow
        of the piecewise-constant force (``p + v dt + a dt^2 / 2``) with the time of impact
        refined to the root of the gap along that flow (see *Exact integrator* in the module
        notes). ``"exact"`` needs an impulse model and ``toi="both"``.
    dtype, device
        Floating point type (``torch.float64`` by default) and device of all tensors.
    **model_options
        Options of a contact model given by name (``stiffness``, ``damping`` of
        ``compliant``; ``iterations`` of ``pbd``); not with an instance.

    Attributes
    ----------
    x0 : torch.Tensor
        Initial state ``(nx,)`` in the hybridoc layout ``[p_1, ..., p_n, v_1, ..., v_n]``.
    radii, masses : torch.Tensor
        ``(n,)`` disc radii and masses.
    restitution : torch.Tensor
        Scalar coefficient of restitution.
    targets : torch.Tensor
        ``(n, 2)`` target positions (rows of discs without a target are ignored).
    model : ContactModel
        The contact model.

    Notes
    -----
    The scene parameters are plain tensor attributes: replace them by tensors that require
    grad (same shape, dtype and device) to differentiate with respect to them, e.g.
    ``sim.radii = torch.tensor([0.2, 0.2], dtype=torch.float64, requires_grad=True)``.
    """

    def __init__(
        self,
        scene: ProblemLike,
        *,
        contact: ContactModel | str = "direct",
        toi: str | None = None,
        integrator: str = "symplectic-euler",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        **model_options: Any,
    ) -> None:
        super().__init__()
        torch_threads()
        scene = disc_scene(scene)
        model = contact_model(contact, toi=toi, **model_options)
        if integrator not in INTEGRATORS:
            raise SceneError(
                f"unknown integrator {integrator!r}; choose one of {', '.join(INTEGRATORS)}"
            )
        if integrator == "exact" and not model.exact_ready:
            raise SceneError("integrator 'exact' needs an impulse model with toi='both'")
        if dtype not in (torch.float32, torch.float64):
            raise SceneError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.scene = scene
        self.model = model
        self.integrator = integrator
        self.dtype = dtype
        self.device = torch.device(device)
        self.n = scene.n_discs
        self.nx = 4 * self.n
        self.nu = scene.n_controls
        self.steps = scene.steps
        self.dt = scene.dt
        self.control_weight = scene.control_weight

        t = self._tensor
        self.x0 = t(scene.initial_state())
        self.radii = t([d.radius for d in scene.discs])
        self.masses = t([d.mass for d in scene.discs])
        self.restitution = t(scene.restitution)
        self.targets = t([d.target if d.target is not None else (0.0, 0.0) for d in scene.discs])
        self.target_mask = t([1.0 if d.target is not None else 0.0 for d in scene.discs])
        self.wall_points = t(np.array([w.point for w in scene.walls]).reshape(-1, 2))
        self.wall_normals = t(np.array([w.normal for w in scene.walls]).reshape(-1, 2))

        # contact incidence (C, n): +1 on disc i, -1 on disc j for pair (i, j); +1 on the
        # disc of a wall contact; in the one contact order of hybridoc.problems.physics
        n, nw = self.n, len(scene.walls)
        cl = ph.contacts(n, nw)
        pairs = [(c.i, c.j) for c in cl if c.is_pair]
        walls = [(c.i, c.wall) for c in cl if not c.is_pair]
        self.n_pairs, self.n_wall_contacts = len(pairs), len(walls)
        self.n_contacts = len(cl)
        S = np.zeros((self.n_contacts, n))
        for k, (i, j) in enumerate(pairs):
            S[k, i], S[k, j] = 1.0, -1.0
        for k, (i, _) in enumerate(walls):
            S[len(pairs) + k, i] = 1.0
        self.incidence = t(S)
        dev = self.device
        self._pair_i = torch.tensor([i for i, _ in pairs], dtype=torch.long, device=dev)
        self._pair_j = torch.tensor([j for _, j in pairs], dtype=torch.long, device=dev)
        self._wall_disc = torch.tensor([i for i, _ in walls], dtype=torch.long, device=dev)
        self._wall_idx = torch.tensor([k for _, k in walls], dtype=torch.long, device=dev)
        # B (n, nu/2): which disc each control pair acts on
        act = scene.actuated_indices
        Bm = np.zeros((n, len(act)))
        for k, i in enumerate(act):
            Bm[i, k] = 1.0
        self._B = t(Bm)

    # ------------------------------------------------------------------ helpers
    @property
    def toi(self) -> str | None:
        """The model's time-of-impact correction (``None`` for non-impulse models)."""
        return getattr(self.model, "toi", None)

    @property
    def contact(self) -> str:
        """The contact model's name."""
        return self.model.name

    def _tensor(self, x: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x, dtype=float), dtype=self.dtype, device=self.device)

    def extra_repr(self) -> str:
        return f"scene={self.scene.name!r}, contact={self.model.label}, dtype={self.dtype}"

    def _check_controls(self, controls: Any) -> tuple[torch.Tensor, bool]:
        if isinstance(controls, torch.Tensor):
            u = controls
        else:
            from hybridoc.ocp import as_float_array

            u = torch.as_tensor(as_float_array(controls, "controls", error=ControlsError))
        if u.is_complex() or u.dtype == torch.bool:
            raise ControlsError("controls must be real numbers")
        u = u.to(dtype=self.dtype, device=self.device)
        batched = u.ndim == 3
        if u.ndim == 2:
            u = u.unsqueeze(0)
        if u.ndim != 3 or u.shape[1:] != (self.steps, self.nu):
            raise ControlsError(
                f"controls must have shape (N, nu) = ({self.steps}, {self.nu}) or "
                f"(B, {self.steps}, {self.nu}), got {tuple(torch.as_tensor(controls).shape)}"
            )
        if not torch.isfinite(u).all():
            raise ControlsError("controls contain NaN or infinite values")
        return u, batched

    def accelerations(self, u: torch.Tensor) -> torch.Tensor:
        """Accelerations ``(B, n, 2)`` of the discs under controls ``u`` of shape ``(B, nu)``."""
        force = torch.einsum("ik,bka->bia", self._B, u.reshape(u.shape[0], -1, 2))
        return force / self.masses[:, None]

    # ------------------------------------------------------------------ geometry
    def relative(self, p: torch.Tensor) -> torch.Tensor:
        """Per-contact relative quantity ``S p``: ``p_i - p_j`` (pairs) or ``p_i`` (walls)."""
        return torch.einsum("ck,bka->bca", self.incidence, p)

    def gap_normal(self, rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gap ``(B, C)`` and unit normal ``(B, C, 2)`` from relative positions ``(B, C, 2)``."""
        ops = ph.TORCH
        P = self.n_pairs
        gaps, normals = [], []
        if P:
            R = self.radii[self._pair_i] + self.radii[self._pair_j]
            g, nrm = ph.pair_gap(rel[:, :P], R, ops)
            gaps.append(g)
            normals.append(nrm)
        if self.n_wall_contacts:
            nw = self.wall_normals[self._wall_idx].expand(rel.shape[0], -1, -1)
            a = self.wall_points[self._wall_idx]
            gaps.append(ph.wall_gap(rel[:, P:], a, nw, self.radii[self._wall_disc], ops))
            normals.append(nw)
        return torch.cat(gaps, 1), torch.cat(normals, 1)

    def gaps(self, p: torch.Tensor) -> torch.Tensor:
        """Signed gaps ``(B, C)`` of all potential contacts at positions ``p`` ``(B, n, 2)``."""
        return self.gap_normal(self.relative(p))[0]

    def impact_time(
        self,
        rel_p: torch.Tensor,
        rel_v: torch.Tensor,
        rel_a: torch.Tensor,
        tau: torch.Tensor,
        active: torch.Tensor,
    ) -> torch.Tensor:
        """Newton refinement of the contact time ``tau`` on the exact flow of the relative
        positions (:func:`hybridoc.problems.physics.refine_impact_time`)."""
        ops, P, dt = ph.TORCH, self.n_pairs, self.dt
        parts = []
        if P:
            R = self.radii[self._pair_i] + self.radii[self._pair_j]
            parts.append(
                ph.refine_impact_time(
                    rel_p[:, :P],
                    rel_v[:, :P],
                    rel_a[:, :P],
                    tau[:, :P],
                    active[:, :P],
                    dt,
                    ops,
                    R=R,
                    iterations=NEWTON_ITERATIONS,
                )  # fmt: skip
            )
        if self.n_wall_contacts:
            nw = self.wall_normals[self._wall_idx]
            off = (self.wall_points[self._wall_idx] * nw).sum(-1) + self.radii[self._wall_disc]
            parts.append(
                ph.refine_impact_time(
                    rel_p[:, P:],
                    rel_v[:, P:],
                    rel_a[:, P:],
                    tau[:, P:],
                    active[:, P:],
                    dt,
                    ops,
                    normal=nw,
                    offset=off,
                    iterations=NEWTON_ITERATIONS,
                )  # fmt: skip
            )
        return torch.cat(parts, 1)

    # ------------------------------------------------------------------ the step
    def step(
        self, p: torch.Tensor, v: torch.Tensor, acc: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step from positions/velocities ``(B, n, 2)`` under accelerations ``(B, n, 2)``."""
        return self.model.torch_step(self, p, v, acc)

    # ------------------------------------------------------------------ rollout and loss
    def _initial(self, x0: Any, batch: int) -> torch.Tensor:
        x = self.x0 if x0 is None else torch.as_tensor(x0, dtype=self.dtype, device=self.device)
        if x.shape[-1] != self.nx or x.ndim not in (1, 2):
            raise ControlsError(
                f"x0 must have shape ({self.nx},) or (B, {self.nx}), got {tuple(x.shape)}"
            )
        if x.ndim == 2 and x.shape[0] not in (1, batch):
            raise ControlsError(
                f"x0 has batch size {x.shape[0]} but the controls have {batch}: give one x0 "
                f"({self.nx},) for all, or one row per batch entry"
            )
        return x.expand(batch, self.nx)

    def rollout(self, controls: Any, x0: Any = None) -> torch.Tensor:
        """Simulate the N steps.

        Parameters
        ----------
        controls
            ``(B, N, nu)`` or ``(N, nu)`` forces of the actuated discs (piecewise constant).
        x0
            Initial state ``(nx,)`` or ``(B, nx)``; default :attr:`x0`.

        Returns
        -------
        torch.Tensor
            States ``(B, N + 1, nx)`` (``B = 1`` for unbatched controls) in the hybridoc
            layout ``[p_1, ..., p_n, v_1, ..., v_n]``.
        """
        u, _ = self._check_controls(controls)
        B, n = u.shape[0], self.n
        x = self._initial(x0, B)
        p = x[:, : 2 * n].reshape(B, n, 2)
        v = x[:, 2 * n :].reshape(B, n, 2)
        states = [x]
        for k in range(self.steps):
            p, v = self.step(p, v, self.accelerations(u[:, k]))
            states.append(torch.cat([p.reshape(B, -1), v.reshape(B, -1)], 1))
        return torch.stack(states, 1)

    forward = rollout

    def terminal_cost(self, states: torch.Tensor) -> torch.Tensor:
        """``phi(s_N) = sum_i |p_i(T) - target_i|^2`` over discs with a target, ``(B,)``."""
        pN = states[:, -1, : 2 * self.n].reshape(-1, self.n, 2)
        return (ph.target_cost(pN, self.targets, ph.TORCH) * self.target_mask).sum(-1)

    def running_cost(self, controls: Any) -> torch.Tensor:
        """``sum_n eps |u_n|^2 dt`` (paper Eq. 8), ``(B,)``."""
        u, _ = self._check_controls(controls)
        return self.control_weight * self.dt * (u**2).sum((1, 2))

    def loss(self, controls: Any, x0: Any = None) -> torch.Tensor:
        """The discrete objective ``phi(s_N) + sum_n eps |u_n|^2 dt`` (paper Eq. 8).

        Returns a tensor of shape ``(B,)`` for batched controls, a scalar for ``(N, nu)``.
        """
        u, batched = self._check_controls(controls)
        out = self.terminal_cost(self.rollout(u, x0)) + self.running_cost(u)
        return out if batched else out[0]

    # ------------------------------------------------------------------ feedback policies
    def policy_controls(
        self, policy: Callable[..., Any], t: float, x: torch.Tensor
    ) -> torch.Tensor:
        """Call a batched feedback policy at time ``t`` on states ``x`` ``(B, nx)``.

        Parameters
        ----------
        policy
            ``(t, state) -> u`` taking ``t`` of shape ``(B,)`` and ``state`` of shape
            ``(B, nx)`` (torch tensors of :attr:`dtype`) and returning ``(B, nu)``.
        t
            The time.
        x
            The states.

        Returns
        -------
        torch.Tensor
            ``(B, nu)`` controls.

        Raises
        ------
        ControlsError
            When the policy raises, returns another shape, or a non-finite value.
        """
        B = x.shape[0]
        tt = torch.full((B,), float(t), dtype=self.dtype, device=self.device)
        try:
            u = policy(tt, x)
        except Exception as exc:  # the user's code: report it as a user error
            raise ControlsError(
                f"the policy raised {type(exc).__name__} at t = {t:.6g}: {exc}"
            ) from exc
        if not isinstance(u, torch.Tensor):
            raise ControlsError(
                f"the policy must return a torch tensor of shape (B, nu) = ({B}, {self.nu}) in "
                f"the simulator, got {type(u).__name__} at t = {t:.6g}"
            )
        if tuple(u.shape) != (B, self.nu):
            raise ControlsError(
                f"the policy returned shape {tuple(u.shape)} at t = {t:.6g}; expected "
                f"(B, nu) = ({B}, {self.nu}) for states of shape {tuple(x.shape)}"
            )
        if u.is_complex() or not u.is_floating_point():
            raise ControlsError(f"the policy returned {u.dtype} values; expected real numbers")
        u = u.to(self.dtype)
        if not bool(torch.isfinite(u).all()):
            raise ControlsError(f"the policy returned a non-finite control at t = {t:.6g}")
        return u

    def rollout_policy(
        self, policy: Callable[..., Any], x0: Any = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Simulate the N steps in closed loop under a feedback policy (zero-order hold).

        At each grid time ``t_n = n dt`` the policy is called on the current states,
        ``u_n = pi(t_n, s_n)``, and the control is held over the step, as the judge's
        ``hold="zoh"`` does. The rollout is differentiable with respect to the policy's
        parameters (and ``x0``).

        Parameters
        ----------
        policy
            A batched policy ``(t, state) -> u``: ``t`` of shape ``(B,)`` and ``state`` of
            shape ``(B, nx)`` in, ``(B, nu)`` out (e.g. a ``torch.nn.Module``).
        x0
            Initial states ``(B, nx)`` or ``(nx,)``; default :attr:`x0`.

        Returns
        -------
        states : torch.Tensor
            ``(B, N + 1, nx)`` states.
        controls : torch.Tensor
            ``(B, N, nu)`` controls the policy returned.

        Raises
        ------
        ControlsError
            A wrong ``x0`` shape or non-finite ``x0``, or a policy that raises, returns the
            wrong shape or a non-finite value.
        """
        if x0 is None:
            x = self.x0[None, :]
        else:
            if not isinstance(x0, torch.Tensor):
                from hybridoc.ocp import as_float_array

                x0 = as_float_array(x0, "x0", error=ControlsError)
            x = torch.as_tensor(x0).to(dtype=self.dtype, device=self.device)
            if x.ndim == 1:
                x = x[None, :]
            if x.ndim != 2 or x.shape[1] != self.nx or x.shape[0] < 1:
                raise ControlsError(
                    f"x0 must have shape ({self.nx},) or (B, {self.nx}), got {tuple(x0.shape)}"
                )
            if not bool(torch.isfinite(x).all()):
                raise ControlsError("x0 contains NaN or infinite values")
        B, n = x.shape[0], self.n
        p = x[:, : 2 * n].reshape(B, n, 2)
        v = x[:, 2 * n :].reshape(B, n, 2)
        grid = self.scene.time_grid()
        states, controls = [x], []
        for k in range(self.steps):
            u = self.policy_controls(policy, float(grid[k]), x)
            controls.append(u)
            p, v = self.step(p, v, self.accelerations(u))
            x = torch.cat([p.reshape(B, -1), v.reshape(B, -1)], 1)
            states.append(x)
        return torch.stack(states, 1), torch.stack(controls, 1)

    def policy_loss(self, policy: Callable[..., Any], x0: Any = None) -> torch.Tensor:
        """Mean over the batch of the discrete objective of the closed-loop rollout.

        The same objective as :meth:`loss`, ``phi(s_N) + sum_n eps |u_n|^2 dt``, with the
        controls ``u_n = pi(t_n, s_n)`` of :meth:`rollout_policy`.

        Parameters
        ----------
        policy
            A batched policy, as in :meth:`rollout_policy`.
        x0
            Initial states ``(B, nx)`` or ``(nx,)``; default :attr:`x0`.

        Returns
        -------
        torch.Tensor
            A scalar: the mean loss over the ``B`` initial states.
        """
        states, u = self.rollout_policy(policy, x0)
        running = self.control_weight * self.dt * (u**2).sum((1, 2))
        return (self.terminal_cost(states) + running).mean()
