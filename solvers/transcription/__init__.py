"""Multi-phase direct transcription of a hybrid OCP (Legendre-Gauss-Radau collocation).

For a given event sequence ``gamma_1 < ... < gamma_K`` (guard names) the problem splits into
``K + 1`` phases with free durations ``h_k > 0``, ``sum h_k = T``. Each phase is divided into
``M`` elements (equal, until the default mesh's error-driven refinement halves those where
the collocation defects are large); on each element the state is a polynomial of degree
``d`` through the element start and the ``d`` Radau points (the last one is the element
end), the dynamics are collocated at the Radau points and the running cost is integrated by
the ``d``-point Radau rule (exact for polynomials of degree ``2 d - 2``). Phases are linked
by the guard ``psi(s(gamma-)) = 0``, the approach condition ``d psi/dt <= 0`` and the reset
``s(gamma+) = g(s(gamma-))``; every other guard stays non-negative at the nodes, so the
transcribed trajectory has no collision outside the sequence. IPOPT (bundled with CasADi)
solves the NLP with exact second derivatives.

Control bounds ``u_min <= u <= u_max`` bound the Radau-point controls, and the Bernstein
coefficients of each element's control polynomial too, so that the polynomial ``u(t)`` that
is returned (and judged) stays within the bounds between the Radau points as well; path
constraints ``c(s, u) >= 0`` hold at the Radau points and phase starts (between them the
judge may find small violations, which shrink with the mesh).

Costates come from the NLP multipliers: the multiplier ``mu_j`` of the collocation defect
``sum_r D_rj X_r - h_e f(X_j, U_j)`` at Radau point ``j`` gives ``lambda(t_j) = -mu_j / w_j``
(``w_j`` the Radau weight), and the multiplier of the initial condition and of each reset
link gives ``lambda(0)`` and ``lambda(gamma_k+)`` exactly (they are sensitivities of the
optimal cost). For disc scenes the optimal flows are polynomials of degree <= 3 in time, so
degree-3 collocation represents the optimum exactly and the answers agree with the HMP
reference to round-off.

Units
    The NLP is built in the problem's own units (:attr:`HybridOCP.scales
    <hybridoc.ocp.HybridOCP.scales>`, issue #32): its variables are the scaled states
    ``(s - s0) / sigma_s``, controls ``u / sigma_u`` and phase durations ``h / sigma_t``, its
    objective ``J / sigma_J``; the collocation defects, the initial condition and the reset links
    are divided by the state scales (a link is written as the jump ``g(s) - s``, so that the
    components a reset keeps link exactly, without the rounding of ``s0 + sigma_s s~``), each
    guard's rows (the guard, free space, the approach condition) by that guard's scale (the
    power of two at or below the norm of its gradient in the scaled state: the length for a
    disc's gap). Multipliers, costates and the result are given back in the problem's units,
    and dt's own tolerances (the refinement's, the comparison with a known cheaper control,
    the guess's perturbation, the bound tolerance) are relative to the scales. So the same
    physical problem in other units or moved gives the same answer: tests/test_units_dt.py
    checks lengths, times and masses scaled by ``1e-6`` to ``1e6`` and moves of up to ``1e6``
    lengths (cost times ``L**2`` within ``1e-9``, the same events and status). A problem whose
    scales are the identity is transcribed exactly as before. A scene moved by more than
    about ``1e6`` of its own lengths has its positions rounded to ``eps |s|``: IPOPT's
    acceptable level and the refinement's tolerance are raised above that rounding
    (``eps max |s0| / sigma_s``), and the answer is as good as the data.

Modules
    The package's modules, by concern: :mod:`~hybridoc.solvers.transcription.options` (the
    options, :class:`DTOptions`), :mod:`~hybridoc.solvers.transcription.collocation` (Radau
    tables, the control polynomials), :mod:`~hybridoc.solvers.transcription.nlp` (the NLP of
    one sequence), :mod:`~hybridoc.solvers.transcription.guess` (initial guesses and candidate
    sequences), :mod:`~hybridoc.solvers.transcription.ipopt` (IPOPT and the result collected),
    :mod:`~hybridoc.solvers.transcription.result` (:class:`DTResult`),
    :mod:`~hybridoc.solvers.transcription.monitor` (progress, time limit, interrupts),
    :mod:`~hybridoc.solvers.transcription.judging` (a candidate judged),
    :mod:`~hybridoc.solvers.transcription.refine` (mesh refinement and the error estimate),
    :mod:`~hybridoc.solvers.transcription.claims` (the status a result may claim) and
    :mod:`~hybridoc.solvers.transcription.solve` (:func:`solve_dt`, the ``"dt"`` method). This
    module re-exports their public names.
"""

from __future__ import annotations

from hybridoc.solvers.transcription.collocation import control_function, resample_controls
from hybridoc.solvers.transcription.ipopt import solve_dt_sequence
from hybridoc.solvers.transcription.nlp import MAX_NLP_SIZE, nlp_size
from hybridoc.solvers.transcription.options import MAX_DEGREE, MAX_MESH, DTOptions
from hybridoc.solvers.transcription.refine import DEFECT_TOL, MAX_ADAPTIVE_MESH, REFINE_RTOL
from hybridoc.solvers.transcription.result import DTResult
from hybridoc.solvers.transcription.solve import METHOD, run_dt, solve_dt

__all__ = [
    "DEFECT_TOL",
    "MAX_ADAPTIVE_MESH",
    "MAX_DEGREE",
    "MAX_MESH",
    "MAX_NLP_SIZE",
    "REFINE_RTOL",
    "METHOD",
    "DTOptions",
    "DTResult",
    "control_function",
    "nlp_size",
    "resample_controls",
    "run_dt",
    "solve_dt",
    "solve_dt_sequence",
]
