"""The HMP shooting system of one event sequence, compiled in CasADi.

The package's modules, by concern: :mod:`~hybridoc.reference.shooting.common` (caches,
problem checks, arc laws), :mod:`~hybridoc.reference.shooting.flow` (the generic
state-costate flow and its DOP853 phases), :mod:`~hybridoc.reference.shooting.core` (the
unknowns and the residual of one sequence), :mod:`~hybridoc.reference.shooting.disc` (the
closed-form phases of a linear control flow and their NLP),
:mod:`~hybridoc.reference.shooting.system` (:class:`ShootingSystem`),
:mod:`~hybridoc.reference.shooting.refinement` (Newton and the accuracy control) and
:mod:`~hybridoc.reference.shooting.arcs` (saturation and path-constraint arcs). This module
re-exports their public names.

For a fixed sequence of guards ``k_1, ..., k_K`` the hybrid minimum principle (DESIGN.md
section 2) is a square nonlinear system in::

    z = [lambda(0), (gamma_k, pi_k, lambda(gamma_k+)) for k = 1..K]

with residuals, in the same order::

    transversality      lambda(T) - grad phi(s(T))                       (nx)
    per event k:        psi_k(s(gamma_k-))                                (1)
                        lambda(gamma_k-) - Dg^T lambda(gamma_k+) - pi_k grad psi_k   (nx)
                        H(gamma_k-) - H(gamma_k+)                         (1)

where the phases between events carry ``(s, lambda)`` forward under ``u = argmin_u H``.
Taking ``lambda(gamma+)`` as an unknown (a light multiple shooting) avoids inverting the
reset Jacobian, which is singular for restitution 0.

Terminal constraints and a free final time (DESIGN.md section 6)
    With terminal equalities ``h_eq(s(T)) = 0`` (``m_e`` of them) and inequalities
    ``h_in(s(T)) >= 0`` (``m_i``), ``z`` ends with their multipliers ``nu`` and ``mu``, and
    transversality reads ``lambda(T) - grad phi + Dh_eq^T nu + Dh_in^T mu = 0`` (the
    Lagrangian ``phi - nu . h_eq - mu . h_in``, so ``mu >= 0``); the residual gains
    ``h_eq(s(T))`` and, per inequality, the Fischer-Burmeister function
    ``mu + h - sqrt(mu^2 + h^2)``, zero exactly when ``mu >= 0``, ``h >= 0`` and
    ``mu h = 0``, smooth wherever strict complementarity holds (one compiled system, no
    active-set loop). With a free final time ``T`` is the last unknown and the last
    residual is ``H(s(T), lambda(T), u*(T))``: the derivative of the optimal cost with
    respect to ``T`` (an autonomous problem, ``phi`` independent of ``T``). A final time at
    one of its bounds is solved with ``T`` fixed there
    (:func:`~hybridoc.reference.sequence.solve_sequence` checks the sign of ``H(T)``).

Control bounds (DESIGN.md section 6)
    ``u* = clip(argmin H, u_min, u_max)`` (a diagonal control weight). Each phase is split
    into arcs on which every component is free or saturated, each saturation
    switch is an unknown time (after the terminal multipliers, before a free ``T``) with
    ``argmin H_i = bound`` as its equation, and every arc has its own law and DOP853 steps,
    so the kinks of the clip never fall inside a step. :func:`saturate` finds the arcs (an
    active-set loop from an extremal of the clipped law).

Path constraints (DESIGN.md section 6)
    Mixed constraints ``c(s, u) = a(s) + B(s) u >= 0`` add one entry per row to an arc's
    law: ignored, active (``c_r = 0``; ``u`` and the multiplier ``nu`` in closed form from
    the constant control weight) or enforced (the pointwise
    minimum of ``H`` over the constraint set: the dense output's law). On an active arc the
    costate follows ``-(H_s - c_s^T nu)``; each junction is an unknown time with
    ``c_r(s, u*) = 0`` under the law without the row. :func:`saturate` finds these arcs as
    it finds the saturated ones, and :func:`arc_mismatch` checks them (``nu >= 0``).

Compiled once per problem structure
    The initial state and the horizon are parameters of the compiled functions, so problems
    that differ only in their data (:meth:`hybridoc.HybridOCP.replace`, a sweep over initial
    states) share them. A disc scene's residual is compiled once per number of events,
    each event's guard chosen by a parameter, so every sequence of one length shares it.

Phase maps
    Disc scenes integrate exactly: ``lambda_p`` is constant, ``lambda_v`` linear, hence
    ``u = -A^T lambda_v / (2 eps)`` is linear in time (``A = M^-1 B``) and the positions are
    cubic. Every other problem (its Hamiltonian quadratic in ``u``) integrates the
    state-costate system and the running cost by fixed steps of Dormand and Prince's
    eighth-order Runge-Kutta method (DOP853's 12-stage formula, :func:`dop853_step`), ``n_k``
    steps on phase ``k`` of its (symbolic) length. One step is compiled per problem
    structure; a phase of ``n`` steps repeats it (``mapaccum``), so every sequence and
    every number of steps shares it and a new sequence costs milliseconds to build. When
    the state-costate system is linear with a nilpotent matrix (double integrators under
    gravity: the bouncing ball, the paddle) its solution is a low-degree polynomial and one
    step per phase is exact (the method's error terms all vanish), to rounding.

Accuracy control
    After Newton converges, :func:`refine` estimates each phase's integration error by step
    doubling (``n_k`` against ``2 n_k`` steps from the same phase start) and weighs it by
    what it does to the cost: the running-cost error plus ``|lambda| . |error of s|`` at the
    phase end (the costate is the cost's sensitivity to the state). Where the sum exceeds
    :data:`ACCURACY_SAFETY` ``* rtol * |J|``, the phases that need it get more steps (the
    eighth order predicts how many, in powers of two), Newton polishes the point again, and
    so on up to :data:`MAX_SUBSTEPS` steps per phase. The judge's re-simulation
    (:func:`~hybridoc.reference.sequence.verify_reference`) is the final arbiter of ``rtol``.
    No CVODES sensitivity solve per Newton step.

Globalisation (disc scenes)
    Because the optimal control is linear in time between events, the optimum also solves a
    small NLP in the event times and the two coefficients of ``u`` per phase. IPOPT solves
    it from a crude guess; its adjoint costates start Newton on the HMP system. Other
    problems are globalised by the direct transcription with the sequence fixed
    (:mod:`hybridoc.reference.solve`).
"""

from __future__ import annotations

from hybridoc.reference.shooting.arcs import (
    SATURATION_ROUNDS,
    SATURATION_SAMPLES,
    SATURATION_TOL,
    TOUCH_TOL,
    arc_mismatch,
    detect_arcs,
    path_multipliers,
    saturate,
    saturation_check,
    saturation_mismatch,
)
from hybridoc.reference.shooting.common import (
    ArcLaw,
    Arcs,
    NewtonResult,
    clip_mode,
    fischer_burmeister,
    free_mode,
    global_law,
    hamiltonian_check,
    has_closed_form_phases,
    is_disc_scene,
    path_check,
    path_rows,
    reset_control_check,
    reset_controls,
    state_rows,
    terminal_sizes,
)
from hybridoc.reference.shooting.core import (
    EVENT_CONTROL_SAMPLES,
)
from hybridoc.reference.shooting.disc import DiscCore as _DiscCore  # noqa: F401  (tests build one)
from hybridoc.reference.shooting.disc import (
    prepare,
)
from hybridoc.reference.shooting.flow import (
    SUBSTEPS,
    SUBSTEPS_POLYNOMIAL,
    dop853_step,
)
from hybridoc.reference.shooting.refinement import (
    ACCURACY_SAFETY,
    DEFAULT_RTOL,
    MAX_SUBSTEPS,
    Refinement,
    newton,
    refine,
)
from hybridoc.reference.shooting.system import (
    ShootingSystem,
    shooting_system,
)

__all__ = [
    "ACCURACY_SAFETY",
    "ArcLaw",
    "Arcs",
    "DEFAULT_RTOL",
    "EVENT_CONTROL_SAMPLES",
    "MAX_SUBSTEPS",
    "NewtonResult",
    "Refinement",
    "SATURATION_ROUNDS",
    "SATURATION_SAMPLES",
    "SATURATION_TOL",
    "SUBSTEPS",
    "SUBSTEPS_POLYNOMIAL",
    "ShootingSystem",
    "TOUCH_TOL",
    "arc_mismatch",
    "clip_mode",
    "detect_arcs",
    "dop853_step",
    "fischer_burmeister",
    "free_mode",
    "global_law",
    "hamiltonian_check",
    "has_closed_form_phases",
    "is_disc_scene",
    "newton",
    "path_check",
    "path_multipliers",
    "path_rows",
    "prepare",
    "refine",
    "reset_control_check",
    "reset_controls",
    "saturate",
    "saturation_check",
    "saturation_mismatch",
    "shooting_system",
    "state_rows",
    "terminal_sizes",
]
