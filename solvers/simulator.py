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
    treatment), ``lcp`` and ``convex`` (:mod:`hybridoc.solvers.impulses`) couple them. The
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

Non-impulse models
    ``contact="compliant"`` (penalty spring-damper) and ``contact="pbd"`` (position-based
    projection) delegate the whole step to :mod:`hybridoc.solvers.penalty`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, SceneError

__all__ = ["Simulator", "TOI_MODES", "IMPULSE_METHODS", "CONTACT_MODELS", "INTEGRATORS"]

TOI_MODES = ("none", "position", "velocity", "both")
INTEGRATORS = ("symplectic-euler", "exact")
NEWTON_ITERATIONS = 4
"""Newton iterations refining the time of impact of the exact integrator (quadratic
convergence from the linear estimate, whose error is O(a dt^2))."""
IMPULSE_METHODS = ("direct", "lcp", "convex")
CONTACT_MODELS = ("compliant", "pbd")


def _load_scene(scene: Any) -> Any:
    from hybridoc.problems import load_scene

    return load_scene(scene)


class Simulator(torch.nn.Module):
    """Differentiable symplectic-Euler simulator of a disc scene.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`, a built-in scene name or a TOML path.
    impulse
        Impulse solver of the impulse-based models: ``"direct"`` (default), ``"lcp"`` or
        ``"convex"``.
    toi
        Time-of-impact correction: ``"none"``, ``"position"``, ``"velocity"`` or ``"both"``
        (default, the paper's method).
    contact
        ``None`` (impulse-based, default), ``"compliant"`` or ``"pbd"``. For convenience the
        impulse method names are accepted here too (``contact="lcp"`` means impulse-based
        with the LCP solver).
    integrator
        ``"symplectic-euler"`` (default, the paper's scheme) or ``"exact"``: the exact flow
        of the piecewise-constant force (``p + v dt + a dt^2 / 2``) with the time of impact
        refined to the root of the gap along that flow (see *Exact integrator* in the module
        notes). ``"exact"`` needs an impulse-based model and ``toi="both"``.
    dtype, device
        Floating point type (``torch.float64`` by default) and device of all tensors.
    stiffness, damping
        Spring stiffness and damping of the compliant model (default: the defaults of
        :func:`hybridoc.solvers.penalty.compliant_step`).
    pbd_iterations
        Projection iterations of the PBD model (default: that of
        :func:`hybridoc.solvers.penalty.pbd_step`).

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

    Notes
    -----
    The scene parameters are plain tensor attributes: replace them by tensors that require
    grad (same shape, dtype and device) to differentiate with respect to them, e.g.
    ``sim.radii = torch.tensor([0.2, 0.2], dtype=torch.float64, requires_grad=True)``.
    """

    def __init__(
        self,
        scene: Any,
        *,
        impulse: str = "direct",
        toi: str = "both",
        contact: str | None = None,
        integrator: str = "symplectic-euler",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        stiffness: float | None = None,
        damping: float | None = None,
        pbd_iterations: int | None = None,
    ) -> None:
        super().__init__()
        scene = _load_scene(scene)
        if contact in IMPULSE_METHODS:
            impulse, contact = contact, None
        if contact is not None and contact not in CONTACT_MODELS:
            raise SceneError(
                f"unknown contact model {contact!r}; choose one of "
                f"{', '.join(IMPULSE_METHODS + CONTACT_MODELS)}"
            )
        if impulse not in IMPULSE_METHODS:
            raise SceneError(
                f"unknown impulse solver {impulse!r}; choose one of {', '.join(IMPULSE_METHODS)}"
            )
        if toi not in TOI_MODES:
            raise SceneError(f"unknown toi setting {toi!r}; choose one of {', '.join(TOI_MODES)}")
        if integrator not in INTEGRATORS:
            raise SceneError(
                f"unknown integrator {integrator!r}; choose one of {', '.join(INTEGRATORS)}"
            )
        if integrator == "exact" and (contact is not None or toi != "both"):
            raise SceneError("integrator 'exact' needs an impulse-based model and toi='both'")
        if dtype not in (torch.float32, torch.float64):
            raise SceneError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
        self.scene = scene
        self.impulse = impulse
        self.toi = toi
        self.contact = contact
        self.integrator = integrator
        self.dtype = dtype
        self.device = torch.device(device)
        if contact is not None:
            from hybridoc.solvers import penalty

            stiffness = penalty.DEFAULT_STIFFNESS if stiffness is None else stiffness
            damping = penalty.DEFAULT_DAMPING if damping is None else damping
            if pbd_iterations is None:
                pbd_iterations = penalty.DEFAULT_PBD_ITERATIONS
        self.stiffness = stiffness
        self.damping = damping
        self.pbd_iterations = pbd_iterations
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

        # Contact incidence S (C, n): +1 on disc i, -1 on disc j for pair (i, j); +1 on the
        # disc of a wall contact. Pairs first (i < j, scene order), then disc-wall, disc-major:
        # the order of the HybridOCP guards.
        n, nw = self.n, len(scene.walls)
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
        walls = [(i, k) for i in range(n) for k in range(nw)]
        self.n_pairs, self.n_wall_contacts = len(pairs), len(walls)
        self.n_contacts = len(pairs) + len(walls)
        S = np.zeros((self.n_contacts, n))
        for c, (i, j) in enumerate(pairs):
            S[c, i], S[c, j] = 1.0, -1.0
        for c, (i, _) in enumerate(walls):
            S[len(pairs) + c, i] = 1.0
        self._S = t(S)
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
    def _tensor(self, x: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x, dtype=float), dtype=self.dtype, device=self.device)

    def extra_repr(self) -> str:
        model = self.contact or f"impulse={self.impulse}, toi={self.toi}"
        return f"scene={self.scene.name!r}, {model}, dtype={self.dtype}"

    def _check_controls(self, controls: Any) -> tuple[torch.Tensor, bool]:
        u = torch.as_tensor(controls)
        if not torch.is_floating_point(u):
            u = u.to(self.dtype)
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
    def _relative(self, p: torch.Tensor) -> torch.Tensor:
        """Per-contact relative quantity ``S p``: ``p_i - p_j`` (pairs) or ``p_i`` (walls)."""
        return torch.einsum("ck,bka->bca", self._S, p)

    def _gap_normal(self, rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Gap ``(B, C)`` and unit normal ``(B, C, 2)`` from relative positions ``(B, C, 2)``."""
        P = self.n_pairs
        gaps, normals = [], []
        if P:
            dp = rel[:, :P]
            dist = torch.linalg.vector_norm(dp, dim=-1)
            gaps.append(dist - (self.radii[self._pair_i] + self.radii[self._pair_j]))
            normals.append(dp / dist[..., None])
        if self.n_wall_contacts:
            nw = self.wall_normals[self._wall_idx].expand(rel.shape[0], -1, -1)
            a = self.wall_points[self._wall_idx]
            gaps.append(((rel[:, P:] - a) * nw).sum(-1) - self.radii[self._wall_disc])
            normals.append(nw)
        return torch.cat(gaps, 1), torch.cat(normals, 1)

    def gaps(self, p: torch.Tensor) -> torch.Tensor:
        """Signed gaps ``(B, C)`` of all potential contacts at positions ``p`` ``(B, n, 2)``."""
        return self._gap_normal(self._relative(p))[0]

    # ------------------------------------------------------------------ the step
    def step(
        self, p: torch.Tensor, v: torch.Tensor, acc: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step from positions/velocities ``(B, n, 2)`` under accelerations ``(B, n, 2)``."""
        dt = self.dt
        if self.contact == "compliant":
            from hybridoc.solvers.penalty import compliant_step

            return compliant_step(
                p, v, acc, dt, self.radii, 1.0 / self.masses, self.wall_points,
                self.wall_normals, stiffness=self.stiffness, damping=self.damping,
            )  # fmt: skip
        if self.contact == "pbd":
            from hybridoc.solvers.penalty import pbd_step

            return pbd_step(
                p, v, acc, dt, self.radii, 1.0 / self.masses, self.wall_points,
                self.wall_normals, self.restitution, iterations=self.pbd_iterations,
            )  # fmt: skip
        exact = self.integrator == "exact"
        v_hat = v + acc * dt
        p_hat = p + (v + 0.5 * acc * dt) * dt if exact else p + v_hat * dt
        if self.n_contacts == 0:
            return p_hat, v_hat
        rel_p_hat = self._relative(p_hat)
        rel_v_hat = self._relative(v_hat)
        d_hat, n_hat = self._gap_normal(rel_p_hat)
        w_hat = (rel_v_hat * n_hat).sum(-1)
        active = (d_hat < 0) & (w_hat < 0)
        if not bool(active.any()):
            return p_hat, v_hat
        # safe denominator: torch.where does not stop NaN gradients of the unused branch
        w_safe = torch.where(active, w_hat, -torch.ones_like(w_hat))
        toi = torch.where(active, torch.clamp(d_hat / w_safe, 0.0, dt), torch.zeros_like(w_hat))
        if exact:
            rel_p, rel_v, rel_a = self._relative(p), self._relative(v), self._relative(acc)
            tau = self._impact_time(rel_p, rel_v, rel_a, dt - toi, active)
            toi = torch.where(active, dt - tau, torch.zeros_like(tau))
            t_ = tau[..., None]
            _, nrm = self._gap_normal(rel_p + (rel_v + 0.5 * rel_a * t_) * t_)
            w = ((rel_v + rel_a * t_) * nrm).sum(-1)
        elif self.toi in ("velocity", "both"):
            tau = (dt - toi)[..., None]
            rel_p_bar = self._relative(p) + tau * rel_v_hat
            rel_v_bar = self._relative(v) + tau * self._relative(acc)
            _, nrm = self._gap_normal(rel_p_bar)
            w = (rel_v_bar * nrm).sum(-1)
        else:
            nrm, w = n_hat, w_hat
        inv_m = 1.0 / self.masses
        if self.impulse == "direct":
            W_diag = (self._S**2) @ inv_m  # (C,): 1/m_i + 1/m_j or 1/m_i
            approaching = active & (w < 0)
            lam = torch.where(
                approaching, -(1.0 + self.restitution) * w / W_diag, torch.zeros_like(w)
            )
        else:
            from hybridoc.solvers.impulses import solve_impulses

            J = self._S[None, :, :, None] * nrm[:, :, None, :]  # (B, C, n, 2)
            W = torch.einsum("bcka,k,bdka->bcd", J, inv_m, J)
            lam = solve_impulses(self.impulse, W, w, active, self.restitution)
        # velocity change of each contact on each disc: (B, C, n, 2)
        dv_c = (lam[..., None, None] * self._S[None, :, :, None]) * nrm[:, :, None, :]
        dv_c = dv_c * inv_m[:, None]
        v_next = v_hat + dv_c.sum(1)
        p_next = p_hat
        if self.toi in ("position", "both"):
            p_next = p_hat + (toi[..., None, None] * dv_c).sum(1)
        return p_next, v_next

    def _impact_time(
        self,
        rel_p: torch.Tensor,
        rel_v: torch.Tensor,
        rel_a: torch.Tensor,
        tau: torch.Tensor,
        active: torch.Tensor,
    ) -> torch.Tensor:
        """Newton refinement of the contact time ``tau`` (after the step start) on the exact
        flow ``D(t) = D_p + D_v t + D_a t^2 / 2`` of the relative position: the root of
        ``|D|^2 - R^2`` (pairs) or ``(D - a) . n - r`` (walls), clipped to ``[0, dt]``."""
        P = self.n_pairs
        R = self.radii[self._pair_i] + self.radii[self._pair_j]
        nw = self.wall_normals[self._wall_idx]
        off = (self.wall_points[self._wall_idx] * nw).sum(-1) + self.radii[self._wall_disc]
        for _ in range(NEWTON_ITERATIONS):
            t_ = tau[..., None]
            D = rel_p + (rel_v + 0.5 * rel_a * t_) * t_
            dD = rel_v + rel_a * t_
            g = torch.cat([(D[:, :P] ** 2).sum(-1) - R**2, (D[:, P:] * nw).sum(-1) - off], 1)
            dg = torch.cat([2 * (D[:, :P] * dD[:, :P]).sum(-1), (dD[:, P:] * nw).sum(-1)], 1)
            ok = active & (dg < 0)
            dg = torch.where(ok, dg, -torch.ones_like(dg))
            tau = torch.where(ok, torch.clamp(tau - g / dg, 0.0, self.dt), tau)
        return tau

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
        return (((pN - self.targets) ** 2).sum(-1) * self.target_mask).sum(-1)

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
