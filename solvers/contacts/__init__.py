"""Contact models of the differentiable disc simulator: one module per model, one registry.

Every model is a :class:`~hybridoc.solvers.contacts.base.ContactModel` subclass defined in
its own module of this package and registered with
:func:`~hybridoc.solvers.contacts.base.register`. The package imports all of its modules
when first imported, so adding a contact model means adding one file. The simulator, gradient
descent, the CLI's ``--contact`` choices, ``compare-contacts``, ``gradcheck`` and the
documentation all read :data:`CONTACT_MODELS`.

A model is an object that carries its options and its time-of-impact setting
(``LCP(toi="both")``, ``Compliant(stiffness=2e4)``); :func:`contact_model` turns what a
caller passes (a name, ``"lcp/both"`` or an instance) into one, once, at the entry point.
Shared pieces have their own modules: :mod:`~hybridoc.solvers.contacts.impulse` (the impulse
models' step), :mod:`~hybridoc.solvers.contacts.casadi_parts` (their CasADi step) and
:mod:`~hybridoc.solvers.contacts.lcp_solver` (the torch solvers' shared pieces).

Built-in models
    ``direct``, ``lcp`` and ``convex`` are impulse models (velocity jumps at contacts) that
    differ in how they solve for the impulses of several contacts in one step; each takes a
    time-of-impact correction (:data:`TOI_MODES`). ``compliant`` (a penalty spring-damper)
    and ``pbd`` (position-based dynamics) are not impulse models.
"""

from __future__ import annotations

import importlib
import pkgutil

from hybridoc.solvers.contacts.base import (
    CONTACT_MODELS,
    TOI_MODES,
    ContactModel,
    contact_model,
    model_names,
    register,
    unregister,
)
from hybridoc.solvers.contacts.impulse import ImpulseModel

__all__ = [
    "CONTACT_MODELS",
    "TOI_MODES",
    "ContactModel",
    "ImpulseModel",
    "contact_model",
    "model_names",
    "register",
    "unregister",
]

for _info in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_info.name}")
