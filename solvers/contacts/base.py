"""The contact-model interface, the impulse models' time-of-impact step, and the registry."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

from hybridoc.errors import SceneError
from hybridoc.problems import physics as ph

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from hybridoc.problems import Scene
    from hybridoc.solvers.casadi_step import ImpulseInputs
    from hybridoc.solvers.simulator import Simulator

__all__ = [
    "CONTACT_MODELS",
    "INTEGRATORS",
    "SIGN_TOLERANCE",
    "TOI_MODES",
    "ContactModel",
    "ImpulseModel",
    "contact_model",
    "model_names",
    "register",
]

TOI_MODES: tuple[str, ...] = ("none", "position", "velocity", "both")
"""Time-of-impact corrections of the impulse models (DESIGN.md section 3): ``none``,
``position`` (Hu et al. 2020), ``velocity`` (the paper's) and ``both`` (the paper's method)."""

INTEGRATORS: tuple[str, ...] = ("symplectic-euler", "exact")
"""The simulator's integrators: the paper's symplectic Euler and the exact flow of the
piecewise-constant force (impulse models with ``toi="both"`` only)."""

SIGN_TOLERANCE = 1e3
"""Sign decisions of the coupled impulse solvers (active sets, complementarity) allow
``SIGN_TOLERANCE * eps * max|q|``; the torch solvers and their CasADi forms share it so that
both pick the same active set."""

CONTACT_MODELS: dict[str, type[ContactModel]] = {}
"""Every registered contact model, by name, in registration order."""


def register(cls: type[ContactModel]) -> type[ContactModel]:
    """Class decorator: add a contact model to :data:`CONTACT_MODELS` under ``cls.name``."""
    if not getattr(cls, "name", ""):
        raise TypeError(f"{cls.__name__} has no name")
    CONTACT_MODELS[cls.name] = cls
    return cls


def model_names() -> list[str]:
    """The registered model names, in registration order."""
    return list(CONTACT_MODELS)


def contact_model(name: str | ContactModel, **options: Any) -> ContactModel:
    """An instance of the model called ``name`` (``toi`` and model options as keywords).

    ``"lcp/both"`` is accepted for ``contact_model("lcp", toi="both")``.
    """
    if isinstance(name, ContactModel):
        if options:
            raise SceneError("options cannot be given with a contact model instance")
        return name
    if not isinstance(name, str):
        raise SceneError(f"contact model must be a name, got {name!r}")
    base, _, toi = name.partition("/")
    if toi:
        if "toi" in options and options["toi"] not in (None, toi):
            raise SceneError(f"contact model {name!r} conflicts with toi={options['toi']!r}")
        options["toi"] = toi
    cls = CONTACT_MODELS.get(base)
    if cls is None:
        raise SceneError(
            f"unknown contact model {base!r}; choose one of {', '.join(CONTACT_MODELS)}"
        )
    return cls(**options)


class ContactModel(ABC):
    """A contact model: how one time step of the disc simulator treats contacts.

    Subclasses set :attr:`name` and :attr:`summary`, implement :meth:`torch_step`, and are
    registered with :func:`register`. Model options are keyword arguments of ``__init__``.
    For the compiled path a model sets :attr:`compiled` and implements
    :meth:`casadi_next_state`, the expression behind :meth:`casadi_step` (an
    :class:`ImpulseModel`: :meth:`ImpulseModel.casadi_impulses`), equal to
    :meth:`torch_step` to rounding, and :meth:`casadi_unsupported` names any limits.
    """

    name: ClassVar[str] = ""
    summary: ClassVar[str] = ""
    impulse_based: ClassVar[bool] = False
    compiled: ClassVar[bool] = False
    """Whether the model has a CasADi step (:meth:`casadi_step`, the compiled fast path of
    gradient descent)."""

    def __init__(self, **options: Any) -> None:
        if options:
            raise SceneError(
                f"contact model {self.name!r} takes no option(s) {', '.join(sorted(options))}"
            )

    @property
    def label(self) -> str:
        """Display name, e.g. ``"direct/both"`` or ``"compliant"``."""
        return self.name

    def settings(self) -> dict[str, Any]:
        """JSON-ready description (name and options)."""
        return {"contact": self.name}

    @abstractmethod
    def torch_step(
        self, sim: Simulator, p: torch.Tensor, v: torch.Tensor, acc: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step of ``sim`` from positions and velocities ``(B, n, 2)`` under ``acc``."""

    def casadi_unsupported(self, scene: Scene, integrator: str) -> str | None:
        """Why this model has no CasADi step for ``scene`` and ``integrator``, or ``None``.

        Parameters
        ----------
        scene : Scene
            The disc scene.
        integrator : str
            ``"symplectic-euler"`` or ``"exact"``.

        Returns
        -------
        str or None
            A one-line reason (the message of the :class:`~hybridoc.errors.SceneError` that
            :func:`hybridoc.solvers.casadi_step.make_step` raises), ``None`` when supported.
        """
        if integrator not in INTEGRATORS:
            return f"unknown integrator {integrator!r}; choose one of {', '.join(INTEGRATORS)}"
        if not self.compiled:
            have = ", ".join(name for name, cls in CONTACT_MODELS.items() if cls.compiled)
            return (
                f"contact model {self.name!r} has no CasADi form ({have} have one); use the "
                "torch Simulator (path='torch')"
            )
        if integrator == "exact" and not (
            self.impulse_based and getattr(self, "toi", None) == "both"
        ):
            return f"integrator 'exact' needs an impulse model with toi='both', not {self.label}"
        return None

    def casadi_step(
        self, scene: Scene, s: Any, u: Any, integrator: str = "symplectic-euler"
    ) -> Any:
        """The state after one step as a CasADi expression of the state and control symbols.

        Parameters
        ----------
        scene : Scene
            The disc scene.
        s, u : casadi.SX
            State ``(4 n,)`` in the layout ``[p_1, ..., p_n, v_1, ..., v_n]`` and control
            ``(nu,)`` symbols.
        integrator : str
            ``"symplectic-euler"`` or ``"exact"``.

        Returns
        -------
        casadi.SX
            The next state, equal to :meth:`torch_step` on the same numbers to rounding.

        Raises
        ------
        hybridoc.errors.SceneError
            With the reason of :meth:`casadi_unsupported` for a setting the model does not
            serve.
        """
        reason = self.casadi_unsupported(scene, integrator)
        if reason is not None:
            raise SceneError(reason)
        return self.casadi_next_state(scene, s, u, integrator)

    def casadi_next_state(self, scene: Scene, s: Any, u: Any, integrator: str) -> Any:
        """:meth:`casadi_step` for a setting it serves (checked there): the next state as a
        CasADi expression, what a compiled model implements."""
        raise SceneError(f"contact model {self.name!r} has no CasADi step")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.label!r})"


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

    A subclass is named after its impulse solver in
    :func:`hybridoc.solvers.impulses.solve_impulses` (or overrides :meth:`contact_impulses`);
    its CasADi form (:meth:`casadi_impulses`) plugs into the shared CasADi step
    :func:`hybridoc.solvers.casadi_step.step_parts`.
    With the simulator's exact integrator the time of impact is refined by Newton's method on
    the exact flow and the impulse taken at the exact contact state.
    """

    impulse_based = True
    coupled: ClassVar[bool] = False
    """Whether the impulses of a step are solved together (an LCP): the CasADi form then
    enumerates active sets, which limits the number of contacts
    (:func:`hybridoc.solvers.casadi_step.enumeration_unsupported`)."""

    def __init__(self, toi: str = "both", **options: Any) -> None:
        super().__init__(**options)
        if toi not in TOI_MODES:
            raise SceneError(f"unknown toi setting {toi!r}; choose one of {', '.join(TOI_MODES)}")
        self.toi = toi

    @property
    def label(self) -> str:
        return f"{self.name}/{self.toi}"

    def settings(self) -> dict[str, Any]:
        return {"contact": self.name, "toi": self.toi}

    def contact_impulses(
        self, sim: Simulator, nrm: torch.Tensor, w: torch.Tensor, active: torch.Tensor
    ) -> torch.Tensor:
        """Impulses ``(B, C)`` of the detected contacts with normals ``nrm (B, C, 2)``."""
        import torch

        from hybridoc.solvers.impulses import solve_impulses

        J = sim.incidence[None, :, :, None] * nrm[:, :, None, :]  # (B, C, n, 2)
        W = torch.einsum("bcka,k,bdka->bcd", J, 1.0 / sim.masses, J)
        return solve_impulses(self.name, W, w, active, sim.restitution)

    def casadi_unsupported(self, scene: Scene, integrator: str) -> str | None:
        from hybridoc.solvers.casadi_step import enumeration_unsupported

        reason = super().casadi_unsupported(scene, integrator)
        if reason is None and self.coupled:
            reason = enumeration_unsupported(self.label, scene)
        return reason

    def casadi_next_state(self, scene: Scene, s: Any, u: Any, integrator: str) -> Any:
        from hybridoc.solvers.casadi_step import step_parts

        return step_parts(scene, s, u, self.toi, integrator, impulses=self.casadi_impulses).s_next

    def casadi_impulses(self, inputs: ImpulseInputs) -> list[Any]:
        """The impulses of one step in CasADi, one per contact (the CasADi form of
        :meth:`contact_impulses`; :class:`~hybridoc.solvers.casadi_step.ImpulseInputs`)."""
        raise SceneError(f"contact model {self.name!r} has no CasADi impulse solver")

    def impulses(
        self, W: torch.Tensor, w: torch.Tensor, active: torch.Tensor, restitution: torch.Tensor
    ) -> torch.Tensor:
        """Impulses ``(B, C)`` from the Delassus matrix ``W (B, C, C)``, the pre-impact normal
        speeds ``w (B, C)`` and the detected contacts ``active (B, C)``."""
        from hybridoc.solvers.impulses import solve_impulses

        return solve_impulses(self.name, W, w, active, restitution)

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
