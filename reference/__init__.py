"""The reference: optimal control by shooting on the hybrid minimum principle.

See :func:`solve_reference`. The HMP system of one event sequence is in
:mod:`hybridoc.reference.shooting`.
"""

from hybridoc.reference.solve import (
    ReferenceResult,
    reference_control,
    solve_reference,
    verify_reference,
)

__all__ = ["ReferenceResult", "reference_control", "solve_reference", "verify_reference"]
