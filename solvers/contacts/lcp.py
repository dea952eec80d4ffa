"""``lcp``: all detected contacts of a step together, the frictionless linear complementarity
problem with Newton's restitution law, solved exactly by principal pivoting
(:func:`hybridoc.solvers.impulses.solve_lcp`)."""

from __future__ import annotations

from hybridoc.solvers.contacts.base import ImpulseModel, register

__all__ = ["LCP"]


@register
class LCP(ImpulseModel):
    """Coupled impulses from the LCP ``0 <= lambda _|_ w+ + e w- >= 0``."""

    name = "lcp"
    summary = "coupled impulses from the frictionless LCP (principal pivoting)"
