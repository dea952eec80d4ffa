"""The contact-model interface, its options, and the registry.

A contact model is an object that carries its options: ``LCP(toi="both")``,
``Compliant(stiffness=2e4)``. :func:`contact_model` is the one parser of what callers pass
(a name, ``"lcp/both"`` or an instance); everything below it carries the object.
"""

from __future__ import annotations

import inspect
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar

from hybridoc.errors import SceneError

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from hybridoc.problems import Scene
    from hybridoc.solvers.simulator import Simulator

__all__ = [
    "CONTACT_MODELS",
    "INTEGRATORS",
    "SIGN_TOLERANCE",
    "TOI_MODES",
    "ContactModel",
    "contact_model",
    "model_names",
    "register",
    "unregister",
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


def unregister(name: str) -> None:
    """Remove the model called ``name`` from :data:`CONTACT_MODELS` (no error if absent)."""
    CONTACT_MODELS.pop(name, None)


def model_names() -> list[str]:
    """The registered model names, in registration order."""
    return list(CONTACT_MODELS)


def contact_model(spec: str | ContactModel, **options: Any) -> ContactModel:
    """The contact model that ``spec`` names: the one parser of every entry point.

    Parameters
    ----------
    spec : str or ContactModel
        A registered name (``"lcp"``), a name with its time-of-impact setting
        (``"lcp/both"``), or an instance.
    **options
        ``toi`` and the model's options (e.g. ``stiffness`` of ``compliant``). ``toi=None``
        means the model's default; non-impulse models ignore ``toi``. With an instance only
        ``toi`` may be given: the instance itself when it is its own setting (or the model
        has none), else a copy with that setting (:meth:`ContactModel.replace`).

    Returns
    -------
    ContactModel

    Raises
    ------
    hybridoc.errors.SceneError
        An unknown name or option, a ``toi`` that conflicts with ``"name/toi"``, or model
        options given with an instance.
    """
    toi = options.pop("toi", None)
    if isinstance(spec, ContactModel):
        if options:
            raise SceneError("options cannot be given with a contact model instance")
        if toi is None or not spec.impulse_based or toi == getattr(spec, "toi", None):
            return spec
        return spec.replace(toi=toi)
    if not isinstance(spec, str):
        raise SceneError(f"contact model must be a name, got {spec!r}")
    base, _, spec_toi = spec.partition("/")
    if spec_toi:
        if toi not in (None, spec_toi):
            raise SceneError(f"contact model {spec!r} conflicts with toi={toi!r}")
        toi = spec_toi
    cls = CONTACT_MODELS.get(base)
    if cls is None:
        raise SceneError(
            f"unknown contact model {base!r}; choose one of {', '.join(CONTACT_MODELS)}"
        )
    if toi is not None:
        options["toi"] = toi
    return cls(**options)


def _option_names(cls: type) -> list[str]:
    """The named ``__init__`` parameters of ``cls`` and of the bases its ``**options`` reach."""
    names: list[str] = []
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None:
            continue
        if klass is ContactModel or klass is object:
            break
        params = list(inspect.signature(init).parameters.values())[1:]
        names += [
            p.name for p in params
            if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in names
        ]  # fmt: skip
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break
    return names


class ContactModel(ABC):
    """A contact model: how one time step of the disc simulator treats contacts.

    Subclasses set :attr:`name` and :attr:`summary`, implement :meth:`torch_step`, and are
    registered with :func:`register`. Model options are keyword arguments of ``__init__``
    stored as attributes of the same name (the scikit-learn convention): :attr:`options`
    reads them back, so that a model compares, hashes, prints and copies
    (:meth:`replace`) by its class and options. For the compiled path a model sets
    :attr:`compiled` and implements :meth:`casadi_next_state`, the expression behind
    :meth:`casadi_step` (an :class:`~hybridoc.solvers.contacts.impulse.ImpulseModel`:
    ``casadi_impulses``), equal to :meth:`torch_step` to rounding, and
    :meth:`casadi_unsupported` names any limits.
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
    def options(self) -> dict[str, Any]:
        """The model's options, ``{name: value}`` in the order of ``__init__``."""
        return {k: getattr(self, k) for k in _option_names(type(self))}

    def replace(self, **options: Any) -> ContactModel:
        """A copy with some options changed, e.g. ``LCP().replace(toi="none")``.

        Parameters
        ----------
        **options
            New values of options of this model.

        Returns
        -------
        ContactModel
            A new instance of the same class.

        Raises
        ------
        hybridoc.errors.SceneError
            An option the model does not take.
        """
        return type(self)(**{**self.options, **options})

    @property
    def label(self) -> str:
        """Display name, e.g. ``"direct/both"`` or ``"compliant"``."""
        return self.name

    def settings(self) -> dict[str, Any]:
        """JSON-ready description: ``{"contact": name, **options}``."""
        return {"contact": self.name, **self.options}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.options.items())
        return f"{type(self).__name__}({args})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ContactModel):
            return NotImplemented
        return type(self) is type(other) and self.options == other.options

    def __hash__(self) -> int:
        return hash((type(self), tuple(self.options.items())))

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
        if integrator == "exact" and not self.exact_ready:
            return f"integrator 'exact' needs an impulse model with toi='both', not {self.label}"
        return None

    @property
    def exact_ready(self) -> bool:
        """Whether the exact integrator serves this model (impulse models with ``toi="both"``)."""
        return self.impulse_based and getattr(self, "toi", None) == "both"

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
