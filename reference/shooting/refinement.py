"""Newton's method on the shooting system (:func:`newton`) and the accuracy control of the
generic flow's steps per phase (:func:`refine`)."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hybridoc import tolerances
from hybridoc.reference.shooting.common import LEVELS, NewtonResult

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.reference.shooting.system import ShootingSystem


MAX_SUBSTEPS = 2048
"""The most DOP853 steps :func:`refine` gives one phase. A phase that needs more is stiff
for an explicit method (``|eigenvalue| h`` far beyond the method's stability region); the
reference then reports that the tolerance cannot be met rather than running for minutes."""
DEFAULT_RTOL = tolerances.value("shooting")
"""The default relative agreement of the shooting cost and the judge's cost (``rtol``):
the table's ``"shooting"`` tolerance (:mod:`hybridoc.tolerances`)."""
ACCURACY_SAFETY = 0.1
""":func:`refine` brings its estimate of the relative cost error below this fraction of
``rtol``: the judge's own integration (DOP853 at 1e-12) and the estimate's first-order
weighting get the rest."""


@dataclass
class Refinement:
    """Outcome of :func:`refine`."""

    system: ShootingSystem
    newton: NewtonResult
    error: float
    """The estimated relative error of the shooting cost (step doubling, module notes)."""
    reason: str = ""
    """Empty when the estimate is within the target; else why it is not."""

    @property
    def ok(self) -> bool:
        """Whether the extremal is accurate to the target."""
        return not self.reason


def refine(
    system: ShootingSystem,
    nr: NewtonResult,
    *,
    rtol: float = DEFAULT_RTOL,
    tol: float = 1e-10,
    max_substeps: int | None = None,
    verbose: bool = False,
) -> Refinement:
    """Steps per phase added until the integration's cost error is within ``rtol``.

    Parameters
    ----------
    system, nr
        A system and Newton's converged point on it.
    rtol
        The relative cost accuracy wanted; the estimate must come below
        :data:`ACCURACY_SAFETY` times it (module notes).
    tol
        Newton's tolerance at each new number of steps.
    max_substeps
        The most steps one phase may get; default :data:`MAX_SUBSTEPS`.
    verbose
        Print each refinement to stderr.

    Returns
    -------
    Refinement
        The system and Newton point it ends at (the input for disc scenes, whose phases are
        exact), the estimate, and ``reason`` when the target was not met: a phase would
        need more than ``max_substeps`` steps, or Newton failed at a new number of steps.
    """
    S = system
    if S.disc:
        return Refinement(S, nr, 0.0)
    if max_substeps is None:
        max_substeps = MAX_SUBSTEPS
    while True:
        errors, cost = S.phase_errors(nr.z)
        scale = max(abs(cost), 1e-300)
        estimate = float(np.sum(errors)) / scale
        target = ACCURACY_SAFETY * rtol * scale
        levels = tuple(S.arc_levels)
        if not np.all(np.isfinite(errors)):
            return Refinement(S, nr, math.inf, "the integration error estimate is not finite")
        if float(np.sum(errors)) <= target:
            LEVELS.setdefault(S.ocp.structure, {})[tuple(S.sequence), S.core.arcs] = levels
            return Refinement(S, nr, estimate)
        share = target / len(errors)
        new = list(levels)
        for k, e in enumerate(errors):
            if e > share:
                # eighth order: n (e / share)^(1/8) steps, in powers of two, at least twice n
                factor = max(2.0, (e / share) ** (1 / 8))
                new[k] = levels[k] * 2 ** math.ceil(math.log2(factor) - 1e-9)
        if max(new) > max_substeps:
            return Refinement(
                S, nr, estimate,
                f"the integration error of the cost is still {estimate:.1e} relative (rtol "
                f"{rtol:g}) with {max(levels)} DOP853 steps on a phase, and more than "
                f"MAX_SUBSTEPS = {max_substeps} would be needed: the state-costate flow is "
                "too stiff for the reference's explicit integrator at this tolerance; a "
                "looser rtol (--rtol) or method 'dt'",
            )  # fmt: skip
        if verbose:
            print(
                f"  refine {S.sequence}: cost error ~{estimate:.1e} relative (target "
                f"{ACCURACY_SAFETY * rtol:.1e}); steps per phase {levels} -> {tuple(new)}",
                file=sys.stderr,
            )
        S = S.with_levels(tuple(new))
        nr_new = newton(S, nr.z, tol=tol, verbose=verbose)
        if not nr_new.converged:
            return Refinement(
                S, nr, estimate,
                f"Newton did not converge with {tuple(new)} steps per phase (residual "
                f"{nr_new.residual:.2e}) while refining the integration for rtol {rtol:g}",
            )  # fmt: skip
        nr = nr_new


def newton(
    system: ShootingSystem,
    z0: np.ndarray,
    *,
    tol: float = 1e-10,
    max_iter: int = 40,
    min_step: float = 1e-6,
    verbose: bool = False,
) -> NewtonResult:
    """Newton's method with exact Jacobian and a backtracking line search on ``|R|``.

    Iterates until the residual (max norm) stops improving below ``tol`` so the solution is
    polished to rounding; ``converged`` means ``residual <= tol`` with event times in order
    (equal ones allowed) inside ``(0, T)``. The line search gives up below a step of
    ``min_step`` (a larger one makes a hopeless start fail sooner).
    """
    z = np.asarray(z0, dtype=float).copy()
    R, J = system.residual(z)  # non-finite: reported as not converged
    norm = float(np.max(np.abs(R))) if R.size else 0.0
    hist = [norm]
    if verbose:
        print(f"  newton {system.sequence}: it  0  |R|_inf = {norm:.3e}", file=sys.stderr)
    it = 0
    for it in range(1, max_iter + 1):
        if not np.isfinite(norm):
            break
        try:
            with np.errstate(all="ignore"):
                dz = -np.linalg.solve(J, R)
        except np.linalg.LinAlgError:
            dz = -np.linalg.lstsq(J, R, rcond=None)[0]
        if not np.all(np.isfinite(dz)):
            break
        alpha = 1.0
        with np.errstate(over="ignore"):  # a huge residual is a failed trial, not an error
            n2 = float(R @ R)
        while True:
            zn = z + alpha * dz
            Rn, Jn = system.residual(zn)
            with np.errstate(over="ignore", invalid="ignore"):
                ok = np.all(np.isfinite(Rn)) and float(Rn @ Rn) <= (1 - 1e-4 * alpha) * n2
            if ok:
                break
            alpha *= 0.5
            if alpha < min_step or norm <= tol:  # at rounding level: no line search
                break
        new = float(np.max(np.abs(Rn))) if Rn.size else 0.0
        if verbose:
            print(
                f"  newton {system.sequence}: it {it:2d}  |R|_inf = {new:.3e}  step = "
                f"{alpha * np.linalg.norm(dz):.3e}  damping = {alpha:g}",
                file=sys.stderr,
            )
        if not np.isfinite(new) or (norm <= tol and new >= 0.5 * norm) or alpha < min_step:
            # no further progress: keep the best point
            if np.isfinite(new) and new < norm:
                z, R, J, norm = zn, Rn, Jn, new
                hist.append(norm)
            break
        z, R, J, norm = zn, Rn, Jn, new
        hist.append(norm)
        if norm == 0.0:
            break
        if len(hist) > 8 and norm > 0.5 * hist[-6] and norm > tol:
            break  # stagnating far from a root: not this sequence's basin
    _, gam, _, _ = system.unpack(z)
    T = system.horizon_of(z)
    times = np.array([float(g) for g in gam])
    # event times may coincide (simultaneous events); the judge decides whether that is
    # well defined (commuting jumps) when it re-simulates the result
    ordered = bool(
        T > 0
        and np.all(np.diff(times) >= -1e-12 * T)
        and (not times.size or (times[0] > 0 and times[-1] < T))
    )
    return NewtonResult(z, norm, it, bool(norm <= tol and ordered), hist)
