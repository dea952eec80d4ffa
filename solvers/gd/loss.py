"""gd's differentiable objective: the compiled CasADi loss or the torch simulator
(:func:`make_loss`), kept per problem structure, and the multi-start's exploration loss."""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import OptionError
from hybridoc.ocp import HybridOCP, Structure
from hybridoc.problems import scene_of
from hybridoc.solvers.gd.options import INTEGRATORS, PATH_WEIGHT, PATHS, check_choice

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.solvers.contacts import ContactModel


_LOSSES: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _model_key(model: ContactModel) -> tuple[Any, ...]:
    """What identifies a contact model in the loss cache: its class and settings."""
    return (type(model), tuple(sorted((k, repr(v)) for k, v in model.settings().items())))


def is_direct_both(model: ContactModel) -> bool:
    """Whether ``model`` is contact ``direct`` with TOI ``both``: the generic
    time-of-impact simulation's, the only one that applies to problems other than disc
    scenes."""
    return model.name == "direct" and getattr(model, "toi", None) == "both"


def make_loss(
    ocp: HybridOCP,
    contact: str | ContactModel,
    integrator: str,
    path: str = "auto",
    path_weight: float = PATH_WEIGHT,
) -> tuple[Any, str]:
    """The differentiable objective of a problem: ``(loss object, "compiled" | "torch")``.

    Parameters
    ----------
    ocp
        The problem.
    contact
        The contact model (disc scenes): a :class:`~hybridoc.solvers.contacts.ContactModel`,
        or a name for :func:`~hybridoc.solvers.contacts.contact_model` with its defaults.
        Generic problems take only ``direct`` with TOI ``both`` (their time-of-impact
        simulation).
    integrator
        ``"exact"`` or ``"symplectic-euler"`` (disc scenes).
    path
        ``"auto"``, ``"compiled"`` or ``"torch"`` (:data:`PATHS`).
    path_weight
        Weight of the path-constraint penalty.

    Returns
    -------
    tuple
        The loss object and the path taken. A compiled loss has numpy
        ``value_and_grad(controls, x0=None)`` (what gd calls: no torch) and a torch
        ``loss``; the torch simulator only ``loss(controls, x0=None)`` (torch,
        differentiable). Compiled losses are kept per problem structure and settings: building
        one takes milliseconds, but continuation stages and repeated solves reuse it.
    """
    from hybridoc.solvers.contacts import contact_model

    model = contact_model(contact)
    check_choice("path", path, PATHS)
    scene = scene_of(ocp)
    is_disc = scene is not None
    check_choice("integrator", integrator, INTEGRATORS)
    if is_disc:
        # every registered model has a CasADi step, within limits (e.g. the scene's number of
        # contacts for the coupled impulse models): auto falls back to torch outside them
        reason = model.casadi_unsupported(scene, integrator)
        if path == "compiled" and reason is not None:
            raise OptionError(f"no compiled path: {reason}")
        use_compiled = path == "compiled" or (path == "auto" and reason is None)
    else:
        if not is_direct_both(model):
            raise OptionError(
                f"contact models and TOI settings apply to disc scenes; {ocp.name!r} is "
                "simulated by the generic time-of-impact method (contact='direct', toi='both')"
            )
        if integrator != "exact":
            raise OptionError(
                f"integrator {integrator!r} applies to disc scenes; the generic time-of-impact "
                "simulation integrates the flow exactly"
            )
        if path == "torch":
            raise OptionError("the torch simulator simulates disc scenes only; use path='compiled'")
        use_compiled = True
    if not use_compiled:
        from hybridoc.solvers.simulator import Simulator
        from hybridoc.solvers.threads import torch_threads

        torch_threads()  # one torch thread unless HYBRIDOC_THREADS says otherwise

        return Simulator(ocp, contact=model, integrator=integrator), "torch"
    from hybridoc.solvers.compiled import CompiledLoss, per_structure

    key = (
        ocp.steps, ocp.horizon, _model_key(model), integrator, path_weight,
        tuple(ocp.x0.tolist()),
    )  # fmt: skip
    loss = per_structure(
        _LOSSES,
        ocp,
        key,
        lambda: CompiledLoss(
            ocp, model, integrator=integrator if is_disc else None, path_weight=path_weight
        ),
    )
    return loss, "compiled"


def exploration_loss(coarse: HybridOCP) -> Any:
    """The loss the multi-start explores with: the compiled exact simulation, contact
    ``direct`` with TOI ``both`` (kept in the cache of :func:`make_loss`)."""
    from hybridoc.solvers.contacts import contact_model

    return make_loss(coarse, contact_model("direct", toi="both"), "exact")[0]


def torch_value_and_grad(loss_obj: Any) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    """``u -> (loss, gradient)`` of a torch loss (the torch simulator) on numpy arrays."""
    import torch

    def value_and_grad(u: np.ndarray) -> tuple[float, np.ndarray]:
        ut = torch.tensor(u, dtype=torch.float64, requires_grad=True)
        value = loss_obj.loss(ut)
        val = float(value.detach())
        if not math.isfinite(val):
            return val, np.zeros_like(u)
        value.backward()
        return val, ut.grad.numpy().copy()

    return value_and_grad
