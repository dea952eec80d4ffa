"""The reference: optimal control by shooting on the hybrid minimum principle.

See :func:`solve_reference`. The HMP system of one event sequence is in
:mod:`hybridoc.reference.shooting`, the solve of one sequence and its verification in
:mod:`hybridoc.reference.sequence`, where candidate sequences come from in
:mod:`hybridoc.reference.candidates`, and the result type in
:mod:`hybridoc.reference.result`.
"""

from hybridoc.reference.result import ReferenceResult, reference_control
from hybridoc.reference.sequence import verify_reference
from hybridoc.reference.solve import reference_supports, solve_reference

__all__ = [
    "ReferenceResult",
    "reference_control",
    "reference_supports",
    "solve_reference",
    "verify_reference",
]
