"""The impulse models' common step: detection, the time-of-impact corrections and the
velocity jump, in torch and (through :func:`~hybridoc.solvers.contacts.casadi_parts.step_parts`)
in CasADi; each impulse model supplies only its impulse solve."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

from hybridoc.errors import SceneError
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import TOI_MODES, ContactModel
from hybridoc.solvers.contacts.casadi_parts import (
    ImpulseInputs,
    enumeration_unsupported,
    step_parts,
)

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from hybridoc.problems import Scene
    from hybridoc.solvers.simulator import Simulator

__all__ = ["ImpulseModel"]


class ImpulseModel(ContactModel):
    """Impulse models with the paper's time-of-impact corrections (DESIGN.md section 3).

    A contact is *detected* when the step ends in penetration while approaching: gap
    ``d^ < 0`` and normal speed ``w^ < 0`` at the predicted state. Its time of impact is the
    paper's ``toi = d^ / w^`` (:func:`hybridoc.problems.physics.toi_linear`). With ``toi``

    ``none``
        the impulse is computed at the penetrated state and ``p_{n+1} = p^``;
    ``position``
        the same impulse, ``p_{n+1} = p_n + v^ (dt - toi) + v_{n+1} toi``;
    ``velocity``
        the impulse at the collision state ``p_bar = p_n + v^ (dt - toi)``,
        ``v_bar = v_n + a_n (dt - toi)`` with its normal; ``p_{n+1} = p^``;
    ``both``
        the impulse of ``velocity`` and the correction of ``position`` (the paper's method).

    A subclass implements :meth:`impulses` (the torch solve on the Delassus matrix, called by
    :meth:`contact_impulses`, which it may override instead) and, for the compiled path,
    :meth:`casadi_impulses`, which plugs into the shared CasADi step
    :func:`~hybridoc.solvers.contacts.casadi_parts.step_parts`.
    With the simulator's exact integrator the time of impact is refined by Newton's method on
    the exact flow and the impulse taken at the exact contact state.

    Parameters
    ----------
    toi : str
        One of :data:`~hybridoc.solvers.contacts.base.TOI_MODES` (default ``"both"``).
    """

    impulse_based = True
    coupled: ClassVar[bool] = False
    """Whether the impulses of a step are solved together (an LCP): the CasADi form then
    enumerates active sets, which limits the number of contacts
    (:func:`~hybridoc.solvers.contacts.casadi_parts.enumeration_unsupported`)."""
    per_contact: ClassVar[bool] = False
    """Whether each detected approaching contact takes the closed-form two-body impulse on
    its own (``direct``): its branch test is then ``w < 0``, and the CasADi step can freeze
    the branches (:func:`~hybridoc.solvers.contacts.casadi_parts.step_parts`)."""

    def __init__(self, toi: str = "both", **options: Any) -> None:
        super().__init__(**options)
        if toi not in TOI_MODES:
            raise SceneError(f"unknown toi setting {toi!r}; choose one of {', '.join(TOI_MODES)}")
        self.toi = toi

    @property
    def label(self) -> str:
        return f"{self.name}/{self.toi}"

    def impulses(
        self, W: torch.Tensor, w: torch.Tensor, active: torch.Tensor, restitution: Any
    ) -> torch.Tensor:
        """Impulses ``(B, C)`` from the Delassus matrix ``W (B, C, C)``, the pre-impact normal
        speeds ``w (B, C)`` and the detected contacts ``active (B, C)``.

        Parameters
        ----------
        W : torch.Tensor
            Delassus matrices ``J M^-1 J^T``, ``(B, C, C)``.
        w : torch.Tensor
            Pre-impact normal relative velocities ``(B, C)``; negative means approaching.
        active : torch.Tensor
            Bool ``(B, C)``: the contacts collision detection reports; the others get zero.
        restitution : float or torch.Tensor
            A scalar, ``(B,)`` (per batch element) or broadcastable to ``(B, C)``.

        Returns
        -------
        torch.Tensor
            ``lambda >= 0`` of shape ``(B, C)``, differentiable in ``W``, ``w`` and
            ``restitution``.
        """
        raise SceneError(f"contact model {self.name!r} has no torch impulse solver")

    def contact_impulses(
        self, sim: Simulator, nrm: torch.Tensor, w: torch.Tensor, active: torch.Tensor
    ) -> torch.Tensor:
        """Impulses ``(B, C)`` of the detected contacts with normals ``nrm (B, C, 2)``."""
        import torch

        J = sim.incidence[None, :, :, None] * nrm[:, :, None, :]  # (B, C, n, 2)
        W = torch.einsum("bcka,k,bdka->bcd", J, 1.0 / sim.masses, J)
        return self.impulses(W, w, active, sim.restitution)

    def casadi_unsupported(self, scene: Scene, integrator: str) -> str | None:
        reason = super().casadi_unsupported(scene, integrator)
        if reason is None and self.coupled:
            reason = enumeration_unsupported(self.label, scene)
        return reason

    def casadi_next_state(self, scene: Scene, s: Any, u: Any, integrator: str) -> Any:
        return step_parts(scene, s, u, self, integrator).s_next

    def casadi_impulses(self, inputs: ImpulseInputs) -> list[Any]:
        """The impulses of one step in CasADi, one per contact: the CasADi form of
        :meth:`contact_impulses`, from
        :class:`~hybridoc.solvers.contacts.casadi_parts.ImpulseInputs`."""
        raise SceneError(f"contact model {self.name!r} has no CasADi impulse solver")

    def torch_step(
        self, sim: Simulator, p: torch.Tensor, v: torch.Tensor, acc: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        import torch

        ops = ph.TORCH
        dt = sim.dt
        exact = sim.integrator == "exact"
        v_hat = v + acc * dt
        p_hat = p + (v + 0.5 * acc * dt) * dt if exact else p + v_hat * dt
        if sim.n_contacts == 0:
            return p_hat, v_hat
        rel_v_hat = sim.relative(v_hat)
        d_hat, n_hat = sim.gap_normal(sim.relative(p_hat))
        w_hat = ph.normal_speed(rel_v_hat, n_hat, ops)
        active = (d_hat < 0) & (w_hat < 0)
        if not bool(active.any()):
            return p_hat, v_hat
        toi = ph.toi_linear(d_hat, w_hat, dt, active, ops)
        if exact:
            rel_p, rel_v, rel_a = sim.relative(p), sim.relative(v), sim.relative(acc)
            tau = sim.impact_time(rel_p, rel_v, rel_a, dt - toi, active)
            toi = torch.where(active, dt - tau, torch.zeros_like(tau))
            t_ = tau[..., None]
            _, nrm = sim.gap_normal(rel_p + (rel_v + 0.5 * rel_a * t_) * t_)
            w = ph.normal_speed(rel_v + rel_a * t_, nrm, ops)
        elif self.toi in ("velocity", "both"):
            tau = (dt - toi)[..., None]
            rel_p_bar = sim.relative(p) + tau * rel_v_hat
            rel_v_bar = sim.relative(v) + tau * sim.relative(acc)
            _, nrm = sim.gap_normal(rel_p_bar)
            w = ph.normal_speed(rel_v_bar, nrm, ops)
        else:
            nrm, w = n_hat, w_hat
        inv_m = 1.0 / sim.masses
        lam = self.contact_impulses(sim, nrm, w, active)
        # velocity change of each contact on each disc: (B, C, n, 2)
        dv_c = (lam[..., None, None] * sim.incidence[None, :, :, None]) * nrm[:, :, None, :]
        dv_c = dv_c * inv_m[:, None]
        v_next = v_hat + dv_c.sum(1)
        p_next = p_hat
        if exact or self.toi in ("position", "both"):
            p_next = p_hat + (toi[..., None, None] * dv_c).sum(1)
        return p_next, v_next
