"""The reference: optimal control by shooting on the hybrid minimum principle.

See :func:`solve_reference` and its options, :class:`ReferenceOptions`
(:mod:`hybridoc.reference.options`); the search behind it is split by concern in
:mod:`hybridoc.reference.search`: its bookkeeping (``book``), the discovery of sequences
(``discovery``), the enumeration and its worker screens (``enumeration``) and what it
claims (``claims``). The HMP system of one event sequence is in
:mod:`hybridoc.reference.shooting`, the solve of one sequence and its verification in
:mod:`hybridoc.reference.sequence`, the reference's own candidate sequences in
:mod:`hybridoc.reference.candidates`, the protocol of the candidate sources it is given (or
that are registered: the solvers') in :mod:`hybridoc.reference.sources`, and the result type
in :mod:`hybridoc.reference.result`.
A disc scene far from its own units is solved in them (:mod:`hybridoc.reference.units`); the
DOP853 tableau is :mod:`hybridoc.reference.dop853`. The reference imports no solver.

The public names are imported on first use (PEP 562), so that the solvers can register
their candidate sources (:mod:`hybridoc.reference.sources`) without importing CasADi.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.reference.options import ReferenceOptions
    from hybridoc.reference.result import ReferenceResult, reference_control
    from hybridoc.reference.sequence import verify_reference
    from hybridoc.reference.solve import METHOD, reference_supports, solve_reference
    from hybridoc.reference.sources import (
        CandidateSource,
        PhaseCostates,
        Proposal,
        SequenceStarter,
        SourceContext,
        register_source,
        registered_sources,
        unregister_source,
    )
    from hybridoc.reference.warm import warm_extremal

__all__ = [
    "METHOD",
    "CandidateSource",
    "PhaseCostates",
    "Proposal",
    "ReferenceOptions",
    "ReferenceResult",
    "SequenceStarter",
    "SourceContext",
    "reference_control",
    "reference_supports",
    "register_source",
    "registered_sources",
    "solve_reference",
    "unregister_source",
    "verify_reference",
    "warm_extremal",
]

_EXPORTS = {
    "METHOD": "hybridoc.reference.solve",
    "CandidateSource": "hybridoc.reference.sources",
    "PhaseCostates": "hybridoc.reference.sources",
    "Proposal": "hybridoc.reference.sources",
    "ReferenceOptions": "hybridoc.reference.options",
    "ReferenceResult": "hybridoc.reference.result",
    "SequenceStarter": "hybridoc.reference.sources",
    "SourceContext": "hybridoc.reference.sources",
    "reference_control": "hybridoc.reference.result",
    "reference_supports": "hybridoc.reference.solve",
    "register_source": "hybridoc.reference.sources",
    "registered_sources": "hybridoc.reference.sources",
    "solve_reference": "hybridoc.reference.solve",
    "unregister_source": "hybridoc.reference.sources",
    "verify_reference": "hybridoc.reference.sequence",
    "warm_extremal": "hybridoc.reference.warm",
}


def __getattr__(name: str) -> Any:
    where = _EXPORTS.get(name)
    if where is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(where), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
