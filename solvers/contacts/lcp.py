"""``lcp``: all detected contacts of a step together, the frictionless linear complementarity
problem with Newton's restitution law, solved exactly by principal pivoting
(:func:`hybridoc.solvers.impulses.solve_lcp`); in CasADi by enumerating the active sets
(:func:`hybridoc.solvers.casadi_step.enumerated_lcp`)."""

from __future__ import annotations

from typing import Any

from hybridoc.solvers.contacts.base import ImpulseModel, register

__all__ = ["LCP"]


@register
class LCP(ImpulseModel):
    """Coupled impulses from the LCP ``0 <= lambda _|_ w+ + e w- >= 0``."""

    name = "lcp"
    summary = "coupled impulses from the frictionless LCP (principal pivoting)"
    compiled = True
    coupled = True

    def casadi_impulses(self, inputs: Any) -> list[Any]:
        from hybridoc.solvers.casadi_step import enumerated_lcp

        # as solve_lcp: q = (1 + e) w-, and a contact without a mobile body takes no impulse
        q = [(1.0 + inputs.restitution) * w for w in inputs.w]
        eligible = [ims > 0 for ims in inputs.inv_mass_sum]
        return enumerated_lcp(inputs.W, q, inputs.active, eligible)
