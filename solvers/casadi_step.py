"""The simulator's discrete step as a CasADi function, for every contact model.

:func:`make_step` writes one step of :class:`hybridoc.solvers.simulator.Simulator` in CasADi
``SX`` symbols, with ``if_else`` for the contact branches, for any registered contact model
(:meth:`hybridoc.solvers.contacts.ContactModel.casadi_step`). The direct transcription and
the compiled rollout (:mod:`hybridoc.solvers.compiled`) are built from it, so they agree with
the torch simulator to rounding.

The pieces the models' CasADi steps share (the impulse models' :func:`step_parts`, the exact
LCP :func:`enumerated_lcp`, :func:`disc_kinematics`) live with the models, in
:mod:`hybridoc.solvers.contacts.casadi_parts`, and are re-exported here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import casadi as ca

from hybridoc.problem import disc_scene
from hybridoc.solvers.contacts import ContactModel, contact_model
from hybridoc.solvers.contacts.casadi_parts import (
    MAX_ENUMERATED_CONTACTS,
    NEWTON_ITERATIONS,
    ImpulseInputs,
    StepParts,
    disc_kinematics,
    enumerated_lcp,
    enumeration_unsupported,
    step_parts,
)
from hybridoc.solvers.contacts.direct import direct_impulses

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems import DiscOCP, Scene

__all__ = [
    "ImpulseInputs",
    "MAX_ENUMERATED_CONTACTS",
    "NEWTON_ITERATIONS",
    "StepParts",
    "direct_impulses",
    "disc_kinematics",
    "enumerated_lcp",
    "enumeration_unsupported",
    "make_step",
    "step_expression",
    "step_parts",
]


def step_expression(
    scene: Scene,
    s: Any,
    u: Any,
    contact: ContactModel | str = "direct",
    integrator: str = "symplectic-euler",
) -> Any:
    """The next state of one step as a CasADi expression.

    Parameters
    ----------
    scene : Scene
        The disc scene.
    s, u
        State ``(4 n,)`` and control ``(nu,)`` symbols.
    contact : ContactModel or str
        The contact model (default ``direct`` with both TOI corrections), parsed by
        :func:`~hybridoc.solvers.contacts.contact_model`.
    integrator : str
        ``"symplectic-euler"`` or ``"exact"``.

    Returns
    -------
    casadi.SX or casadi.MX
        The state after one step of length ``scene.dt``.
    """
    return contact_model(contact).casadi_step(scene, s, u, integrator)


def make_step(
    scene: Scene | str | DiscOCP,
    contact: ContactModel | str = "direct",
    integrator: str = "symplectic-euler",
    *,
    toi: str | None = None,
) -> ca.Function:
    """The discrete step ``s_next = step(s, u)`` of a scene as a CasADi ``Function``.

    Parameters
    ----------
    scene : Scene, str or DiscOCP
        A :class:`~hybridoc.problems.Scene`, a built-in name, a TOML path or a disc OCP.
    contact : ContactModel or str
        Any registered contact model (:data:`hybridoc.solvers.contacts.CONTACT_MODELS`): an
        instance (``LCP(toi="none")``), a name (``"lcp"``) or ``"lcp/both"``.
    integrator : str
        ``"symplectic-euler"`` (default, the paper's) or ``"exact"`` (impulse models with
        ``toi="both"``).
    toi : str, optional
        Time-of-impact correction of an impulse model given by name (``None``: the model's
        own, ``"both"`` by default); folded into the model by
        :func:`~hybridoc.solvers.contacts.contact_model`.

    Returns
    -------
    casadi.Function
        ``Function('step', [s, u], [s_next])`` with ``SX`` inside, equal to one step of
        :class:`hybridoc.solvers.simulator.Simulator` with the same model.

    Raises
    ------
    SceneError
        An unknown model or setting, or a combination without a CasADi form (one line that
        says why, from :meth:`~hybridoc.solvers.contacts.ContactModel.casadi_unsupported`).
    """
    scene = disc_scene(scene)
    model = contact_model(contact, toi=toi)
    s = ca.SX.sym("s", 4 * scene.n_discs)
    u = ca.SX.sym("u", scene.n_controls)
    s_next = model.casadi_step(scene, s, u, integrator)  # raises the model's reason, if any
    return ca.Function("step", [s, u], [s_next], ["s", "u"], ["s_next"])
