"""The HMP shooting system of one event sequence, compiled in CasADi.

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

import itertools
import math
import sys
import threading
import weakref
from collections.abc import Callable, MutableMapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import casadi as ca
import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP, Structure
from hybridoc.problems.disc_ocp import DiscOCP
from hybridoc.reference import dop853 as tab

__all__ = [
    "ACCURACY_SAFETY",
    "SATURATION_ROUNDS",
    "SATURATION_SAMPLES",
    "SATURATION_TOL",
    "TOUCH_TOL",
    "arc_mismatch",
    "clip_mode",
    "detect_arcs",
    "free_mode",
    "global_law",
    "path_check",
    "path_multipliers",
    "path_rows",
    "reset_control_check",
    "reset_controls",
    "saturate",
    "saturation_check",
    "saturation_mismatch",
    "state_rows",
    "DEFAULT_RTOL",
    "EVENT_CONTROL_SAMPLES",
    "MAX_SUBSTEPS",
    "SUBSTEPS",
    "SUBSTEPS_POLYNOMIAL",
    "NewtonResult",
    "Refinement",
    "ShootingSystem",
    "dop853_step",
    "fischer_burmeister",
    "hamiltonian_check",
    "is_disc_scene",
    "newton",
    "prepare",
    "refine",
    "shooting_system",
    "terminal_sizes",
]

SUBSTEPS_POLYNOMIAL = 1
"""DOP853 steps per phase for linear nilpotent state-costate systems (exact)."""
SUBSTEPS = 4
"""DOP853 steps per phase that other problems start from (:func:`refine` adds more)."""
MAX_SUBSTEPS = 2048
"""The most DOP853 steps :func:`refine` gives one phase. A phase that needs more is stiff
for an explicit method (``|eigenvalue| h`` far beyond the method's stability region); the
reference then reports that the tolerance cannot be met rather than running for minutes."""
DEFAULT_RTOL = 1e-9
"""The default relative agreement of the shooting cost and the judge's cost (``rtol``)."""
ACCURACY_SAFETY = 0.1
""":func:`refine` brings its estimate of the relative cost error below this fraction of
``rtol``: the judge's own integration (DOP853 at 1e-12) and the estimate's first-order
weighting get the rest."""

_CORES: weakref.WeakKeyDictionary[Structure, dict[Any, Any]] = weakref.WeakKeyDictionary()
_FLOWS: weakref.WeakKeyDictionary[Structure, _Flow] = weakref.WeakKeyDictionary()
# the steps per phase each sequence was last accepted at, per structure (where the next
# solve of the same sequence starts)
_LEVELS: weakref.WeakKeyDictionary[Structure, dict[tuple[str, ...], tuple[int, ...]]] = (
    weakref.WeakKeyDictionary()
)
_LOCK = threading.RLock()
_T = TypeVar("_T")


def _built_once(cache: MutableMapping[Any, _T], key: Any, build: Callable[[], _T]) -> _T:
    """``cache[key]``, built by ``build()`` once even when threads ask at the same time
    (the cheap lookup first, the build under the lock)."""
    value = cache.get(key)
    if value is None:
        with _LOCK:
            value = cache.get(key)
            if value is None:
                value = cache[key] = build()
    return value


def is_disc_scene(ocp: HybridOCP) -> bool:
    """Whether ``ocp`` is a compiled disc scene: ``f = (v, A u)``, ``L = eps |u|^2``, without
    terminal constraints, a free final time, path constraints or a reset that depends on the
    control (those take the generic flow, whose phases are exact for the disc scenes'
    polynomial flow too: one DOP853 step each)."""
    return isinstance(ocp, DiscOCP) and not (
        ocp.has_terminal_constraints
        or ocp.free_horizon
        or ocp.path is not None
        or any(g.uses_control for g in ocp.guards)
    )


def hamiltonian_check(ocp: HybridOCP) -> str | None:
    """``None`` when the reference can take ``u* = argmin_u H`` in closed form (a Hamiltonian
    quadratic in ``u`` with a positive definite Hessian), else the reason."""
    s = ca.SX.sym("s", ocp.nx)
    lam = ca.SX.sym("lam", ocp.nx)
    u = ca.SX.sym("u", ocp.nu)
    try:
        H = ocp.L(s, u) + ca.dot(lam, ocp.f(s, u))
    except RuntimeError:
        return "the reference needs f and L as SX-evaluable functions"
    Huu = ca.hessian(H, u)[0]
    if ca.depends_on(Huu, ca.vertcat(u, lam)):
        return "the reference needs a Hamiltonian quadratic in u (L quadratic in u, f affine in u)"
    if ca.depends_on(Huu, s):
        return "the reference needs a control weight (d2L/du2) that does not depend on the state"
    try:
        eig = np.linalg.eigvalsh(np.asarray(ca.evalf(Huu), dtype=float))
    except RuntimeError:
        return "the control weight d2L/du2 is not a constant matrix"
    if eig.size and eig.min() <= 0:
        return "the Hamiltonian must be strictly convex in u (d2L/du2 positive definite)"
    return None


_CHECKED: weakref.WeakKeyDictionary[Structure, str | None] = weakref.WeakKeyDictionary()


def _checked_hamiltonian(ocp: HybridOCP) -> str | None:
    """:func:`hamiltonian_check`, once per structure."""
    if ocp.structure not in _CHECKED:
        _CHECKED[ocp.structure] = hamiltonian_check(ocp)
    return _CHECKED[ocp.structure]


def prepare(ocp: HybridOCP, lengths: Any, max_iter: int = 100) -> None:
    """Disc scenes: build the NLPs of these numbers of events now, so that the worker
    processes a search forks share them instead of each compiling its own; nothing for
    other problems."""
    if is_disc_scene(ocp):
        for K in sorted(set(int(k) for k in lengths)):
            _disc_nlp(ocp, K, max_iter)


def _residual_and_jacobian(F: Any, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate the shooting system; an evaluation failure reads as a non-finite residual."""
    try:
        R, J = (np.asarray(x) for x in F(z))
    except RuntimeError:  # an integrator gives up on a wild trial point: back off
        n = int(F.size1_out(0))
        return np.full(n, np.nan), np.full((n, z.size), np.nan)
    return R.ravel(), J


@dataclass
class NewtonResult:
    """Outcome of :func:`newton`."""

    z: np.ndarray
    residual: float
    iterations: int
    converged: bool
    history: list[float] = field(default_factory=list)


def dop853_step(rhs: ca.Function, n: int) -> ca.Function:
    """One step of Dormand and Prince's eighth-order Runge-Kutta method, ``(x, h) -> x(h)``.

    The 12-stage formula of DOP853 (Hairer, Norsett and Wanner, *Solving Ordinary
    Differential Equations I*, section II.10), with SciPy's coefficients
    (:mod:`hybridoc.reference.dop853`), taken at a fixed step: no error estimate, no
    step-size control (:func:`refine` does that per phase).

    Parameters
    ----------
    rhs
        ``x -> dx/dt`` (autonomous), SX-evaluable.
    n
        The dimension of ``x``.
    """
    # the tableau is kept in reference/dop853.py (SciPy's, bit for bit, tested): importing
    # scipy.integrate for it cost the first solve about 1 s (issue #34)
    stages = tab.N_STAGES
    A = np.zeros((stages, stages))
    for i, row in enumerate(tab.A):
        A[i, : len(row)] = row
    B = np.asarray(tab.B, dtype=float)
    x = ca.SX.sym("x", n)
    h = ca.SX.sym("h")
    K: list[Any] = []
    for i in range(stages):
        xi = x
        for j in range(i):
            if A[i, j] != 0.0:
                xi = xi + (h * A[i, j]) * K[j]
        K.append(rhs(xi))
    inc = ca.SX.zeros(n)
    for i in range(stages):
        if B[i] != 0.0:
            inc = inc + B[i] * K[i]
    return ca.Function("dop853_step", [x, h], [x + h * inc])


# An arc's control law: per component the interval (lo, hi) that argmin H is clipped to:
# (-inf, inf) free, (c, c) saturated at c, (u_min, u_max) clipped. A problem with m path
# constraints c(s, u) >= 0 has m more entries, one per row, the interval c_r is held in:
# (-inf, inf) ignored, (0, 0) active (c_r = 0 with its multiplier), (0, inf) enforced (the
# pointwise minimum of H over the constraint set: the dense output's law).
ArcLaw = tuple[tuple[float, float], ...]
# Per phase (between events), its arcs' laws in time order; consecutive arcs of one phase
# differ in one entry, at a saturation switch or a junction of a path constraint.
Arcs = tuple[tuple[ArcLaw, ...], ...]


def free_mode(nu: int) -> ArcLaw:
    """The unconstrained law ``u* = argmin H`` of ``nu`` components."""
    return ((-math.inf, math.inf),) * nu


def clip_mode(ocp: HybridOCP) -> ArcLaw:
    """The problem's bounds as one law, ``u* = clip(argmin H, u_min, u_max)``."""
    assert ocp.u_min is not None and ocp.u_max is not None
    return tuple((float(a), float(b)) for a, b in zip(ocp.u_min, ocp.u_max, strict=True))


def path_rows(ocp: HybridOCP) -> int:
    """The number of path constraints ``c(s, u) >= 0`` of ``ocp`` (0 without them)."""
    return 0 if ocp.path is None else int(ocp.path.numel_out(0))


def global_law(ocp: HybridOCP) -> ArcLaw:
    """The law of the pointwise constrained minimum of ``H``: ``u*`` minimises ``H`` over
    the bounds and the path constraints (``clip_mode`` with bounds only, ``free_mode``
    without constraints). Right on every arc of a consistent extremal: the dense output's
    law. A pure state row (:func:`state_rows`) is ignored: where it is active is a
    property of the arcs, not of the pointwise minimum."""
    box = clip_mode(ocp) if ocp.has_bounds else free_mode(ocp.nu)
    pure = state_rows(ocp)
    return box + tuple(
        (-math.inf, math.inf) if r in pure else (0.0, math.inf) for r in range(path_rows(ocp))
    )


def path_check(ocp: HybridOCP) -> str | None:
    """``None`` when the reference can take ``ocp``'s path constraints (none; mixed rows
    ``c_r(s, u)`` affine in ``u``; pure state rows ``c_r(s)`` of order 1, whose derivative
    ``c_r,s f(s, u)`` depends on ``u``), else the one-line reason."""
    if ocp.path is None:
        return None
    s, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("u", ocp.nu)
    try:
        c = ocp.path(s, u)
        f = ocp.f(s, u)
    except RuntimeError:
        return "the reference needs the path constraints as an SX-evaluable function"
    high = []
    for r in range(c.numel()):
        if ca.depends_on(c[r], u):
            continue
        order = _state_order(c[r], s, u, f)
        if order != 1:
            high.append((r, order))
    if high:
        rows = ", ".join(
            f"row {r} of order {p}" if p <= _MAX_ORDER else f"row {r} of order > {_MAX_ORDER}"
            for r, p in high
        )
        return (
            f"the HMP reference handles pure state constraints c(s) >= 0 of order 1 only (u "
            f"in dc/dt = c_s f(s, u)); path constraint {rows} (u first appears in a higher "
            "time derivative: its boundary arcs and junction conditions are not modelled); "
            "use method 'dt'"
        )
    if ca.depends_on(ca.jacobian(_effective_rows(c, s, u, f), u), u):
        return (
            "the HMP reference handles path constraints c(s, u) >= 0 affine in u only (then the "
            "constrained minimum of H has a closed form on each arc); use method 'dt'"
        )
    return None


_MAX_ORDER = 3
"""The highest order of a pure state constraint :func:`path_check` names exactly."""


def _state_order(c: Any, s: Any, u: Any, f: Any) -> int:
    """The order of a pure state row ``c(s)``: the first time derivative (along
    ``s' = f(s, u)``) that depends on ``u``; :data:`_MAX_ORDER` ``+ 1`` when none up to
    that does (or when it never does)."""
    d = c
    for p in range(1, _MAX_ORDER + 1):
        d = ca.mtimes(ca.jacobian(d, s), f)
        if ca.depends_on(d, u):
            return p
    return _MAX_ORDER + 1


def _effective_rows(c: Any, s: Any, u: Any, f: Any) -> Any:
    """The rows the arcs hold: a mixed row as it is, a pure state row ``c_r(s)`` as its time
    derivative ``c_r,s f(s, u)`` (indirect adjoining: on a boundary arc ``c_r = 0`` is held
    by ``dc_r/dt = 0``, with ``c_r = 0`` at the entry)."""
    rows = []
    for r in range(c.numel()):
        cr = c[r]
        rows.append(cr if ca.depends_on(cr, u) else ca.mtimes(ca.jacobian(cr, s), f))
    return ca.vertcat(*rows) if rows else ca.SX(0, 1)


def state_rows(ocp: HybridOCP) -> tuple[int, ...]:
    """The path constraint rows of ``ocp`` that do not depend on ``u`` (pure state
    constraints ``c_r(s) >= 0``); empty without path constraints."""
    if ocp.path is None:
        return ()

    def build() -> tuple[int, ...]:
        s, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("u", ocp.nu)
        c = ocp.path(s, u)
        return tuple(r for r in range(c.numel()) if not ca.depends_on(c[r], u))

    return _built_once(_STATE_ROWS, ocp.structure, build)


_STATE_ROWS: weakref.WeakKeyDictionary[Structure, tuple[int, ...]] = weakref.WeakKeyDictionary()


class _Law:
    """One control law of a structure : ``u*``, ``H`` at ``u*``, the
    state-costate right-hand side, its DOP853 step and the phase maps of each number of
    steps."""

    def __init__(self, fl: _Flow, mode: ArcLaw) -> None:
        s, lam, u, H = fl.s_sym, fl.lam_sym, fl.u_sym, fl.H_expr
        nx = fl.nx
        self.mode = mode
        self.nx = nx
        box, rows = mode[: fl.nu], mode[fl.nu :]
        nu_star = ca.SX.zeros(fl.m_path)
        cls = ca.SX.zeros(fl.nu + fl.m_path)
        sig = ca.SX.zeros(fl.m_path)
        if any(r != (-math.inf, math.inf) for r in rows):
            u_star, nu_star, cls, sig = _constrained_minimum(fl, mode)
        elif all(lo == -math.inf and hi == math.inf for lo, hi in box):
            u_star = fl.u_unc_expr
        else:
            comps = []
            for i, (lo, hi) in enumerate(box):
                ui = fl.u_unc_expr[i]
                if lo == hi:
                    ui = ca.SX(lo)
                else:
                    if lo > -math.inf:
                        ui = ca.fmax(ui, lo)
                    if hi < math.inf:
                        ui = ca.fmin(ui, hi)
                comps.append(ui)
            u_star = ca.vertcat(*comps)
        self.u_star = ca.Function("u_star", [s, lam], [u_star])
        self.H_star = ca.Function("H_star", [s, lam], [ca.substitute(H, u, u_star)])
        # path constraints: their multipliers nu (0 where a row is not active), the
        # entries' classes (controls +1/-1 at a bound, rows 1 active) and, per row, a
        # function that changes sign at its junctions (nu where active, -c elsewhere)
        self.path_law = ca.Function("path_law", [s, lam], [nu_star, cls, sig])
        # costate flow -dH/ds at the minimising u (envelope theorem: partial at fixed u);
        # on a constrained arc of the Lagrangian H - nu^T c: -(H_s - c_s^T nu)
        dlam = -ca.substitute(ca.gradient(H, s), u, u_star)
        if fl.m_path and not nu_star.is_zero():
            dlam = dlam + ca.mtimes(ca.substitute(fl.c_s, u, u_star).T, nu_star)
        x = ca.vertcat(s, lam)
        # the running cost rides along as a last component that nothing depends on
        xj = ca.vertcat(x, ca.SX.sym("j"))
        rhs = ca.vertcat(fl.f(s, u_star), dlam, fl.L(s, u_star))
        self.rhs = ca.Function("hmp_rhs", [xj], [rhs])
        self.polynomial = _nilpotent_linear(ca.vertcat(fl.f(s, u_star), dlam), x)
        self.start_steps = SUBSTEPS_POLYNOMIAL if self.polynomial else SUBSTEPS
        self.width = 2 * nx + 1  # s, lambda and the running cost
        self.step = dop853_step(self.rhs, self.width)
        xn = ca.SX.sym("x", self.width)
        tau = ca.SX.sym("tau")
        xe = self.step(xn, tau)
        se, le = xe[:nx], xe[nx : 2 * nx]
        self.dense = ca.Function("hmp_dense", [xn, tau], [se, le, self.u_star(se, le)])
        self.dense_u = ca.Function("hmp_dense_u", [xn, tau], [self.u_star(se, le)])
        self._maps: dict[int, tuple[ca.Function, ca.Function]] = {}

    def _steps(self, n: int) -> tuple[ca.Function, ca.Function]:
        maps = self._maps.get(n)
        if maps is None:
            with _LOCK:
                maps = self._maps.get(n)
                if maps is None:
                    acc = self.step.mapaccum(f"hmp_steps{n}", n)
                    nx = self.nx
                    s0 = ca.MX.sym("s0", nx)
                    l0 = ca.MX.sym("l0", nx)
                    h = ca.MX.sym("h")
                    x0 = ca.vertcat(s0, l0, ca.MX(1, 1))
                    X = acc(x0, ca.repmat(h / n, 1, n))
                    end = X[:, n - 1]
                    phase = ca.Function(
                        f"hmp_phase{n}", [s0, l0, h], [end[:nx], end[nx : 2 * nx], end[2 * nx]]
                    )
                    nodes = ca.Function(f"hmp_nodes{n}", [s0, l0, h], [ca.horzcat(x0, X)])
                    maps = self._maps[n] = (phase, nodes)
        return maps

    def phase(self, n: int) -> ca.Function:
        """``(s0, lambda0, h) -> (s, lambda, running cost)`` after ``n`` steps over ``h``."""
        return self._steps(n)[0]

    def nodes(self, n: int) -> ca.Function:
        """``(s0, lambda0, h) -> (2 nx + 1, n + 1)``: the ``n`` steps' nodes (dense output)."""
        return self._steps(n)[1]


class _Flow:
    """What every sequence of one (non-disc) structure shares: ``argmin H``, the guards,
    ``phi`` and a :class:`_Law` per control law met (the unconstrained one's attributes are
    the flow's own: ``u_star``, ``H_star``, ``rhs``, ``step``, ``dense``, ``phase(n)``, ...)."""

    def __init__(self, ocp: HybridOCP) -> None:
        nx, nu = ocp.nx, ocp.nu
        self.nx, self.nu = nx, nu
        s, lam, u, H, Huu, u_star = _argmin_hamiltonian(ocp)
        self.s_sym, self.lam_sym, self.u_sym, self.H_expr = s, lam, u, H
        self.u_unc_expr = u_star
        self.u_unc = ca.Function("u_unc", [s, lam], [u_star])
        self.H = ca.Function("H", [s, lam, u], [H])
        self.f = ocp.f
        self.L = ocp.L
        # path constraints c(s, u) = a(s) + B(s) u >= 0 (path_check: affine in u) and the
        # constant control weight W = d2H/du2 (hamiltonian_check) of their closed forms
        self.m_path = path_rows(ocp)
        # pure state rows c_r(s) (order 1, path_check) enter the arcs' laws as their time
        # derivative c_r,s f (indirect adjoining); state_fn gives c_r(s) and its gradient
        # for the entry conditions (0 for mixed rows)
        self.state_rows = state_rows(ocp)
        if self.m_path:
            assert ocp.path is not None
            raw = ocp.path(s, u)
            c = _effective_rows(raw, s, u, ocp.f(s, u))
            pure = ca.vertcat(
                *[raw[r] if r in self.state_rows else ca.SX(0) for r in range(self.m_path)]
            )
            self.state_fn = ca.Function("state_rows", [s], [pure, ca.jacobian(pure, s)])
            self.c = ca.Function("path", [s, u], [c])
            self.c_expr = c
            self.c_a = ca.substitute(c, u, ca.DM.zeros(nu))
            self.c_B = ca.jacobian(c, u)
            self.c_s = ca.jacobian(c, s)
            self.W = np.asarray(ca.evalf(Huu), dtype=float)
        self._laws: dict[ArcLaw, _Law] = {}
        free = self.law(free_mode(nu))
        self.u_star, self.H_star = free.u_star, free.H_star
        self.rhs, self.polynomial, self.start_steps = free.rhs, free.polynomial, free.start_steps
        self.width, self.step, self.dense, self.dense_u = (
            free.width, free.step, free.dense, free.dense_u
        )  # fmt: skip
        self.phase, self.nodes = free.phase, free.nodes
        self.guards = []
        # a reset that reads the control takes the event's own control v as a second input;
        # lambda^T g(s, v) and its gradient in v give that control's condition and start
        self.reset_values: list[ca.Function | None] = []
        self.reset_grads: list[ca.Function | None] = []
        v = ca.SX.sym("v", nu)
        for j, g in enumerate(ocp.guards):
            psi = g.psi(s)
            gs = g.reset_at(s, v)
            ins = [s, v] if g.uses_control else [s]
            self.guards.append(
                ca.Function(f"ev{j}", ins, [psi, ca.gradient(psi, s), gs, ca.jacobian(gs, s)])
            )
            if g.uses_control:
                lg = ca.dot(lam, gs)
                self.reset_values.append(ca.Function(f"rv{j}", [s, v, lam], [lg]))
                self.reset_grads.append(ca.Function(f"rg{j}", [s, v, lam], [ca.gradient(lg, v)]))
            else:
                self.reset_values.append(None)
                self.reset_grads.append(None)
        phi = ocp.phi(s)
        self.phi = ca.Function("phi", [s], [phi, ca.gradient(phi, s)])
        self.terminal = _terminal_fn(ocp, s)

    def law(self, mode: ArcLaw) -> _Law:
        """The :class:`_Law` of ``mode``, built once (a law of the controls alone, on a
        problem with path constraints, ignores them)."""
        mode = _full_law(mode, self.nu + self.m_path)
        return _built_once(self._laws, mode, lambda: _Law(self, mode))


def _full_law(mode: ArcLaw, width: int) -> ArcLaw:
    """``mode`` as floats, with an ignored entry for each path constraint it leaves out."""
    mode = tuple((float(lo), float(hi)) for lo, hi in mode)
    return mode + ((-math.inf, math.inf),) * (width - len(mode))


def _constrained_minimum(fl: _Flow, mode: ArcLaw) -> tuple[Any, Any, Any, Any]:
    """``u*``, the path multipliers ``nu``, the classes and the junction functions of a law
    with path constraints (:class:`_Law`), in closed form.

    ``H = u^T W u / 2 + g(s, lambda)^T u + ...`` with ``W`` constant and every constraint
    affine in ``u``: with the rows ``C u = d`` held as equalities (saturated controls
    ``u_i = v``, active rows ``a_r + B_r u = 0``) the minimum is
    ``u = u_unc + W^-1 C^T kappa``, ``(C W^-1 C^T) kappa = d - C u_unc``, and ``nu_r`` is
    ``kappa`` of row ``r`` (stationarity of ``H - nu^T c``). Entries held as inequalities
    (the dense output's law, :func:`global_law`) enumerate their active sets: of the
    candidates that meet every inequality (to rounding), the one of least ``H`` is the
    minimum over the constraint set (the problem is a strictly convex QP).
    """
    u, H = fl.u_sym, fl.H_expr
    nu, m = fl.nu, fl.m_path
    Winv = np.linalg.inv(fl.W)
    u_unc = fl.u_unc_expr
    a, B = fl.c_a, fl.c_B
    # a row: (C (1, nu), d, kind, index, side): kind "u" (a control at a value) or "c"
    eq: list[tuple[Any, Any, str, int, int]] = []
    ineq: list[tuple[Any, Any, str, int, int]] = []
    for i, (lo, hi) in enumerate(mode[:nu]):
        e = ca.DM.zeros(1, nu)
        e[i] = 1.0
        if lo == hi:
            eq.append((e, ca.SX(lo), "u", i, 0))
            continue
        if lo > -math.inf:
            ineq.append((e, ca.SX(lo), "u", i, -1))
        if hi < math.inf:
            ineq.append((e, ca.SX(hi), "u", i, 1))
    for r, (lo, hi) in enumerate(mode[nu:]):
        if (lo, hi) == (0.0, 0.0):
            eq.append((B[r, :], -a[r], "c", r, 1))
        elif (lo, hi) == (0.0, math.inf):
            ineq.append((B[r, :], -a[r], "c", r, 1))
        elif (lo, hi) != (-math.inf, math.inf):
            raise ValueError(f"path constraint {r}: law entry {(lo, hi)} is not one of the three")
    room = nu - len(eq)
    subsets: list[tuple[int, ...]] = [()]
    for k in range(1, max(room, 0) + 1):
        for sub in itertools.combinations(range(len(ineq)), k):
            comps = [ineq[j][3] for j in sub if ineq[j][2] == "u"]
            if len(comps) == len(set(comps)):
                subsets.append(sub)

    def candidate(sub: tuple[int, ...]) -> tuple[Any, Any, Any, Any, Any]:
        rows = eq + [ineq[j] for j in sub]
        if rows:
            C = ca.vertcat(*[r[0] for r in rows])
            d = ca.vertcat(*[r[1] for r in rows])
            M = ca.mtimes(ca.mtimes(C, Winv), C.T)
            kappa = ca.solve(M, d - ca.mtimes(C, u_unc)) if len(rows) > 1 else (
                (d - ca.mtimes(C, u_unc)) / M
            )  # fmt: skip
            us = u_unc + ca.mtimes(ca.mtimes(Winv, C.T), kappa)
        else:
            kappa, us = ca.SX(0, 1), u_unc
        cs = ca.substitute(fl.c_expr, u, us)
        nus = ca.SX.zeros(m)
        for p, row in enumerate(rows):
            if row[2] == "c":
                nus[row[3]] = kappa[p]
        # the worst violation of the inequalities, each relative to its own terms' size
        worst: Any = -ca.inf
        for j, (_, dr, kind, idx, side) in enumerate(ineq):
            if j in sub:
                continue
            if kind == "u":
                gap = (dr - us[idx]) if side < 0 else (us[idx] - dr)
                scale = 1.0 + ca.fabs(dr)
            else:
                gap = -cs[idx]
                scale = 1.0 + ca.fabs(a[idx]) + ca.sum1(ca.fabs(B[idx, :].T * us))
            worst = ca.fmax(worst, gap / scale)
        cls = ca.SX.zeros(nu + m)
        sig = -cs
        for row in rows:
            if row[2] == "u" and row[4]:
                cls[row[3]] = row[4]
            elif row[2] == "c":
                cls[nu + row[3]] = 1
                sig[row[3]] = nus[row[3]]
        return us, nus, cls, sig, (ca.substitute(H, u, us), worst)

    tol = 1e-11  # rounding of the exact candidate's constraints, far below any real gap
    best = candidate(subsets[0])
    u_b, nu_b, cls_b, sig_b, (H_b, V_b) = best
    for sub in subsets[1:]:
        u_c, nu_c, cls_c, sig_c, (H_c, V_c) = candidate(sub)
        # a feasible candidate beats an infeasible one, then the smaller H (the smaller
        # violation between infeasible ones: the dense law stays defined off the set)
        take = ca.if_else(
            V_c <= tol, ca.logic_or(V_b > tol, H_c < H_b), ca.logic_and(V_b > tol, V_c < V_b)
        )
        u_b = ca.if_else(take, u_c, u_b)
        nu_b = ca.if_else(take, nu_c, nu_b)
        cls_b = ca.if_else(take, cls_c, cls_b)
        sig_b = ca.if_else(take, sig_c, sig_b)
        H_b = ca.if_else(take, H_c, H_b)
        V_b = ca.if_else(take, V_c, V_b)
    return u_b, nu_b, cls_b, sig_b


def _terminal_fn(ocp: HybridOCP, s: Any) -> ca.Function | None:
    """``s -> (h_eq, Dh_eq, h_in, Dh_in)`` (empty blocks where a kind is absent), or
    ``None`` without terminal constraints."""
    if not ocp.has_terminal_constraints:
        return None
    parts = []
    for fn in (ocp.terminal_eq, ocp.terminal_ineq):
        h = fn(s) if fn is not None else ca.SX(0, 1)
        parts += [h, ca.jacobian(h, s) if fn is not None else ca.SX(0, ocp.nx)]
    return ca.Function("terminal", [s], parts)


def terminal_sizes(ocp: HybridOCP) -> tuple[int, int]:
    """The numbers of terminal equalities and inequalities of ``ocp``."""
    return tuple(  # type: ignore[return-value]
        0 if fn is None else int(fn.size1_out(0)) for fn in (ocp.terminal_eq, ocp.terminal_ineq)
    )


def fischer_burmeister(a: Any, b: Any) -> Any:
    """``a + b - sqrt(a^2 + b^2)``: zero exactly when ``a >= 0``, ``b >= 0`` and ``a b = 0``."""
    return a + b - ca.sqrt(a**2 + b**2)


def _argmin_hamiltonian(ocp: HybridOCP) -> tuple[Any, Any, Any, Any, Any, Any]:
    """Symbols ``s``, ``lambda``, ``u``, the Hamiltonian ``H = L + lambda^T f``, its control
    weight ``d2H/du2`` and its unconstrained minimiser in ``u`` (exact for the
    quadratic-in-u ``H`` that :func:`hamiltonian_check` admits)."""
    s = ca.SX.sym("s", ocp.nx)
    lam = ca.SX.sym("lam", ocp.nx)
    u = ca.SX.sym("u", ocp.nu)
    H = ocp.L(s, u) + ca.dot(lam, ocp.f(s, u))
    Hu = ca.gradient(H, u)
    Huu = ca.hessian(H, u)[0]
    u_star = -ca.solve(Huu, ca.substitute(Hu, u, ca.DM.zeros(ocp.nu)))
    return s, lam, u, H, Huu, u_star


def _flow(ocp: HybridOCP) -> _Flow:
    return _built_once(_FLOWS, ocp.structure, lambda: _Flow(ocp))


# ------------------------------------------------------------- resets that read the control
_RESET_CONTROLS: weakref.WeakKeyDictionary[Structure, tuple[tuple[int, ...], ...]] = (
    weakref.WeakKeyDictionary()
)


def reset_controls(ocp: HybridOCP) -> tuple[tuple[int, ...], ...]:
    """Per guard of ``ocp``, the control components its reset ``g(s, u)`` reads (empty for a
    reset ``g(s)``): at an event of that guard, the components of the reset's own control
    ``v_k``, which the shooting takes as unknowns."""

    def build() -> tuple[tuple[int, ...], ...]:
        s, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("u", ocp.nu)
        out = []
        for g in ocp.guards:
            gs = g.reset(s, u) if g.uses_control else None
            out.append(() if gs is None else tuple(
                i for i in range(ocp.nu) if ca.depends_on(gs, u[i])
            ))  # fmt: skip
        return tuple(out)

    if not any(g.uses_control for g in ocp.guards):
        return ((),) * len(ocp.guards)
    return _built_once(_RESET_CONTROLS, ocp.structure, build)


def reset_control_check(ocp: HybridOCP) -> str | None:
    """``None`` when the reference can take ``ocp``'s resets (none reads the control, or
    each reset ``g(s, u)`` is SX-evaluable and, in every control component it is affine in,
    bounded on at least one side), else the one-line reason.

    At an event whose reset reads the control, the reset's own control ``v_k`` minimises
    ``lambda(gamma+)^T g(s(gamma-), v)`` over the bounds (module notes); a reset affine in
    an unbounded component has no such minimum (its slope in ``v`` does not vanish in
    general): such a dependence is refused, naming the component."""
    if not any(g.uses_control for g in ocp.guards):
        return None
    s, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("u", ocp.nu)
    lo = np.full(ocp.nu, -np.inf) if ocp.u_min is None else np.asarray(ocp.u_min, dtype=float)
    hi = np.full(ocp.nu, np.inf) if ocp.u_max is None else np.asarray(ocp.u_max, dtype=float)
    for g in ocp.guards:
        if not g.uses_control:
            continue
        try:
            gs = g.reset(s, u)
        except RuntimeError:
            return (
                f"the reference needs the reset of guard {g.name!r} (which reads the control) "
                "as an SX-evaluable function"
            )
        for i in range(ocp.nu):
            if not ca.depends_on(gs, u[i]) or ca.depends_on(ca.jacobian(gs, u[i]), u[i]):
                continue
            if lo[i] == -np.inf and hi[i] == np.inf:
                return (
                    f"the reset of guard {g.name!r} is affine in the control u[{i}], which has "
                    "no bounds: lambda(gamma+)^T g(s, v) is then linear in the reset's own "
                    f"control v and has no minimum over it (no optimum exists); bound u[{i}] "
                    "(u_min, u_max)"
                )
    return None


def _reset_bounds(ocp: HybridOCP) -> tuple[np.ndarray, np.ndarray]:
    """The control bounds as two ``(nu,)`` arrays (infinite where there are none)."""
    lo = np.full(ocp.nu, -np.inf) if ocp.u_min is None else np.asarray(ocp.u_min, dtype=float)
    hi = np.full(ocp.nu, np.inf) if ocp.u_max is None else np.asarray(ocp.u_max, dtype=float)
    return lo, hi


EVENT_CONTROL_SAMPLES = 65
"""Samples per component (up to two components; 4096 points in all beyond) on which the
shooting's start looks for the minimum of ``lambda^T g`` over a reset's own control."""


class _CoreBase:
    """The unknowns of one (structure, sequence) and their layout."""

    def __init__(
        self, ocp: HybridOCP, sequence: list[str], free: bool = False, arcs: Arcs | None = None
    ) -> None:
        names = [g.name for g in ocp.guards]
        unknown = [s for s in sequence if s not in names]
        if unknown:
            raise SceneError(f"unknown guard name(s) {unknown}; this problem has {names}")
        reason = _checked_hamiltonian(ocp)
        if reason:
            raise SceneError(reason)
        self.sequence = list(sequence)
        self.guard_index = [names.index(s) for s in sequence]
        self.K = len(sequence)
        self.nx, self.nu = ocp.nx, ocp.nu
        self.disc = is_disc_scene(ocp)
        self.levels: tuple[int, ...] | None = None
        self.m_eq, self.m_in = terminal_sizes(ocp)
        self.free = bool(free)
        if arcs is None:
            arcs = (((free_mode(ocp.nu)),),) * (self.K + 1)
        self.arcs: Arcs = arcs
        # per phase, (arc, component, value) of each saturation switch, in time order
        self.switches: list[list[tuple[int, int, float]]] = [
            [_switch_of(a, b, k, j) for j, (a, b) in enumerate(zip(p[:-1], p[1:], strict=True))]
            for k, p in enumerate(arcs)
        ]
        self.n_switch = sum(len(w) for w in self.switches)
        # resets that read the control: per event, the components of its own control v_k
        # (unknowns after the switches, before a free T; 0 where the reset reads none)
        comps = reset_controls(ocp)
        self.v_comps: list[tuple[int, ...]] = [comps[j] for j in self.guard_index]
        self.n_v = sum(len(c) for c in self.v_comps)
        self.v_bounds = _reset_bounds(ocp)
        # per phase and switch, the pure state row whose boundary arc the switch enters
        # (-1 for any other switch): there c_r(s) = 0 and the costate jumps by
        # eta grad c_r, with eta an unknown of its own (after the switch times)
        pure = state_rows(ocp)
        self.jump_rows: list[list[int]] = [
            [
                i - self.nu
                if i >= self.nu and i - self.nu in pure and p[j + 1][i] == (0.0, 0.0)
                else -1
                for j, i, _ in w
            ]
            for p, w in zip(arcs, self.switches, strict=True)
        ]
        self.n_eta = sum(r >= 0 for w in self.jump_rows for r in w)
        self._residual_fns: tuple[Any, Any] | None = None
        self._ocp_ref = weakref.ref(ocp)

    @property
    def F(self) -> Any:
        """``(residual, Jacobian)`` of ``(z, x0, T)``; built on first use, since the
        search solves many sequences' NLPs whose Newton step never comes."""
        return self._residual()[0]

    @property
    def traj(self) -> Any:
        """Phase starts, states, costates, costs, ... of ``(z, x0, T)`` (see ``F``)."""
        return self._residual()[1]

    def _residual(self) -> tuple[Any, Any]:
        if self._residual_fns is None:
            ocp = self._ocp_ref()
            if ocp is None:
                raise RuntimeError("the problem of this shooting core no longer exists")
            with _LOCK:
                if self._residual_fns is None:
                    self._residual_fns = self._build_residual(ocp)
        return self._residual_fns

    def _build_residual(self, ocp: HybridOCP) -> tuple[Any, Any]:
        raise NotImplementedError

    @property
    def nz(self) -> int:
        """Number of unknowns."""
        return (
            self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in + self.n_switch
            + self.n_eta + self.n_v + int(self.free)
        )  # fmt: skip

    def unpack_switches(self, z: Any) -> list[list[Any]]:
        """Per phase, its saturation switch times (absolute), in time order."""
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in
        out = []
        for w in self.switches:
            out.append([z[o + i] for i in range(len(w))])
            o += len(w)
        return out

    def unpack_etas(self, z: Any) -> list[list[Any]]:
        """Per phase and switch, the costate jump ``eta`` at the entry of a pure state
        row's boundary arc (0 at any other switch)."""
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in + self.n_switch
        out = []
        for w in self.jump_rows:
            row = []
            for r in w:
                if r >= 0:
                    row.append(z[o])
                    o += 1
                else:
                    row.append(0.0)
            out.append(row)
        return out

    def with_switches(
        self,
        z_base: np.ndarray,
        times: Sequence[Sequence[float]],
        etas: Sequence[Sequence[float]] | None = None,
    ) -> np.ndarray:
        """``z`` of this core from a point of the same sequence without saturation switches
        (``z_base``: multipliers, costates, terminal multipliers and a free ``T``), the
        switch times per phase and, per phase and switch, the costate jumps ``eta`` of the
        entries of pure state rows' boundary arcs (default 0; other switches' are
        ignored)."""
        z_base = np.asarray(z_base, dtype=float)
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in
        flat = [float(t) for w in times for t in w]
        if len(flat) != self.n_switch:
            raise ValueError(f"{self.n_switch} switch times expected, got {len(flat)}")
        jumps = [
            0.0 if etas is None else float(etas[k][j])
            for k, w in enumerate(self.jump_rows)
            for j, r in enumerate(w)
            if r >= 0
        ]
        return np.concatenate([z_base[:o], flat, jumps, z_base[o:]])

    def strip_switches(self, z: np.ndarray) -> np.ndarray:
        """The point without its switch times and entry jumps (:meth:`with_switches`'s
        ``z_base``)."""
        o = self.nx + self.K * (self.nx + 2) + self.m_eq + self.m_in
        return np.concatenate([z[:o], z[o + self.n_switch + self.n_eta :]])

    def entry_jump(self, k: int, i: int, s: Any, lam: Any, eta: Any) -> Any:
        """The costate after switch ``i`` of phase ``k``: ``lambda + eta grad c_r(s)`` at
        the entry of pure state row ``r``'s boundary arc (``lambda(t1-) = lambda(t1+) -
        eta grad c_r``, ``eta >= 0``: the measure ``-d nu`` of the direct adjoining's
        multiplier), ``lambda`` at any other switch."""
        r = self.jump_rows[k][i]
        if r < 0:
            return lam
        grad = self.fl.state_fn(s)[1]
        if isinstance(lam, np.ndarray):
            return lam + float(eta) * np.asarray(grad, dtype=float)[r]
        return lam + eta * grad[r, :].T

    def unpack_event_controls(self, z: Any) -> list[Any]:
        """Per event, the control its reset reads: ``v_k`` (``(nu,)``, its components from
        ``z``, 0 in those the reset does not read) for a reset that reads the control,
        ``None`` for any other."""
        o = self.nz - int(self.free) - self.n_v
        numeric = isinstance(z, np.ndarray)
        out: list[Any] = []
        for comps in self.v_comps:
            if not comps:
                out.append(None)
                continue
            parts: list[Any] = []
            for i in range(self.nu):
                if i in comps:
                    parts.append(z[o])
                    o += 1
                else:
                    parts.append(0.0)
            out.append(np.array(parts, dtype=float) if numeric else ca.vertcat(*parts))
        return out

    def with_event_controls(self, z: np.ndarray, controls: Sequence[Any]) -> np.ndarray:
        """``z`` with the reset controls ``controls`` (per event a ``(nu,)`` control or
        ``None``; only the components each reset reads are taken)."""
        z = np.array(z, dtype=float)
        o = self.nz - int(self.free) - self.n_v
        for comps, v in zip(self.v_comps, controls, strict=True):
            for i in comps:
                if v is not None:
                    z[o] = float(np.asarray(v, dtype=float).ravel()[i])
                o += 1
        return z

    def guard_at(self, k: int, s: Any, v: Any = None) -> Any:
        """``(psi, grad psi, g, Dg)`` of event ``k``'s guard at ``s``: a reset that reads the
        control at ``v`` (``Dg`` its Jacobian in ``s`` there)."""
        fn = self.guard_fns[k]
        return fn(s) if v is None else fn(s, v)

    def event_control_conditions(self, k: int, s: Any, v: Any, lam: Any) -> list[Any]:
        """The conditions of event ``k``'s reset control ``v`` at ``s(gamma-)`` and
        ``lambda(gamma+)``: per component ``i`` it reads, with ``d_i = d/dv_i lambda^T
        g(s, v)``, ``v_i - clip(v_i - d_i, lo_i, hi_i)``: zero exactly when ``d_i = 0``
        inside the bounds, ``d_i >= 0`` at the lower bound and ``d_i <= 0`` at the upper one
        (the first-order conditions of the box-constrained minimum; ``d_i`` alone without
        bounds). One system decides which bounds are active, as the Fischer-Burmeister
        terms do for terminal inequalities."""
        comps = self.v_comps[k]
        if not comps:
            return []
        d = self.reset_grads[k](s, v, lam)
        lo, hi = self.v_bounds
        out = []
        for i in comps:
            if lo[i] == -math.inf and hi[i] == math.inf:
                out.append(d[i])
                continue
            w = v[i] - d[i]
            if lo[i] > -math.inf:
                w = ca.fmax(w, float(lo[i]))
            if hi[i] < math.inf:
                w = ca.fmin(w, float(hi[i]))
            out.append(v[i] - w)
        return out

    def start_event_control(
        self, k: int, s: np.ndarray, lam: np.ndarray, hint: Any = None
    ) -> np.ndarray | None:
        """A start for event ``k``'s reset control at ``s(gamma-)`` and ``lambda(gamma+)``:
        the least ``lambda^T g(s, v)`` over samples of the bounds of the components the
        reset reads (:data:`EVENT_CONTROL_SAMPLES`; a side without a bound sampled up to
        100 from the other), the pointwise minimum the HMP asks of ``v``; ``hint`` (default
        0 clipped into the bounds) where no sample is lower. ``None`` for a reset that does
        not read the control."""
        comps = self.v_comps[k]
        if not comps:
            return None
        lo, hi = self.v_bounds
        base = np.zeros(self.nu) if hint is None else np.array(hint, dtype=float).ravel()
        base = np.clip(base, lo, hi)
        axes = []
        for i in comps:
            a, b = lo[i], hi[i]
            n = EVENT_CONTROL_SAMPLES
            far = np.concatenate([[0.0], np.logspace(-3, 2, n - 1)])
            if math.isfinite(a) and math.isfinite(b):
                axes.append(np.linspace(a, b, n))
            elif math.isfinite(a):
                axes.append(a + far)
            elif math.isfinite(b):
                axes.append(b - far)
            else:
                axes.append(np.concatenate([-far[:0:-1], far]))
        if len(axes) <= 2:
            grid = np.array(list(itertools.product(*axes)), dtype=float)
        else:
            rng = np.random.default_rng(0)
            grid = np.column_stack([rng.choice(ax, 4096) for ax in axes])
        V = np.repeat(base[None, :], grid.shape[0] + 1, axis=0)
        V[1:, list(comps)] = grid
        fn = self.reset_values[k]
        vals = np.asarray(
            fn.map(V.shape[0])(np.repeat(np.asarray(s, float).reshape(-1, 1), V.shape[0], 1),
                               V.T, np.repeat(np.asarray(lam, float).reshape(-1, 1),
                                              V.shape[0], 1)),
            dtype=float,
        ).ravel()  # fmt: skip
        vals = np.where(np.isfinite(vals), vals, np.inf)
        j = int(np.argmin(vals))
        if not vals[j] < vals[0] - 1e-12 * (1.0 + abs(vals[0])):
            return base
        return V[j]

    def horizon(self, z: Any, T: Any) -> Any:
        """The final time at ``z``: its last entry when free, else the parameter ``T``."""
        return z[self.nz - 1] if self.free else T

    def unpack_terminal(self, z: Any) -> tuple[Any, Any]:
        """The terminal multipliers ``nu`` (equalities) and ``mu`` (inequalities)."""
        o = self.nx + self.K * (self.nx + 2)
        return z[o : o + self.m_eq], z[o + self.m_eq : o + self.m_eq + self.m_in]

    def unpack(self, z: Any) -> tuple[Any, list[Any], list[Any], list[Any]]:
        """``lambda(0)``, event times, multipliers, post-event costates."""
        nx = self.nx
        lam0 = z[:nx]
        gam, pis, lps = [], [], []
        for k in range(self.K):
            o = nx + k * (nx + 2)
            gam.append(z[o])
            pis.append(z[o + 1])
            lps.append(z[o + 2 : o + 2 + nx])
        return lam0, gam, pis, lps

    def pack(
        self,
        lam0: np.ndarray,
        gam: Any,
        pis: Any,
        lps: Any,
        nu: Any = None,
        mu: Any = None,
        T: float | None = None,
        v: Sequence[Any] | None = None,
    ) -> np.ndarray:
        """Inverse of :meth:`unpack` (and :meth:`unpack_terminal`) for numbers: the terminal
        multipliers default to 0, a free final time to ``T`` (required then), the reset
        controls (per event ``(nu,)`` or ``None``, :meth:`unpack_event_controls`) to 0
        clipped into the bounds."""
        parts = [np.asarray(lam0, float).ravel()]
        for k in range(self.K):
            parts += [[float(gam[k]), float(pis[k])], np.asarray(lps[k], float).ravel()]
        parts.append(np.zeros(self.m_eq) if nu is None else np.asarray(nu, float).ravel())
        parts.append(np.zeros(self.m_in) if mu is None else np.asarray(mu, float).ravel())
        if self.n_switch:
            raise ValueError("a point with saturation switches is made by with_switches()")
        lo, hi = self.v_bounds
        for k, comps in enumerate(self.v_comps):
            given = None if v is None or v[k] is None else np.asarray(v[k], float).ravel()
            parts.append(np.array(
                [float(np.clip(0.0 if given is None else given[i], lo[i], hi[i])) for i in comps]
            ))  # fmt: skip
        if self.free:
            if T is None:
                raise ValueError("a free final time needs its value in pack(T=...)")
            parts.append(np.array([float(T)]))
        return np.concatenate(parts)

    def _assemble(
        self, ocp: HybridOCP, phase: Any, sym: Any, extra: Sequence[Any] = ()
    ) -> tuple[ca.Function, ca.Function]:
        """The residual (with its Jacobian) and the trajectory function, from ``phase(k, s,
        lambda, h) -> (s, lambda, running cost)`` and the symbol type ``sym``; ``extra``:
        symbols the pieces read besides ``(z, x0, T)``, inputs after them."""
        nx = self.nx
        z = sym.sym("z", self.nz)
        x0 = sym.sym("x0", nx)
        T_par = sym.sym("T")
        T = self.horizon(z, T_par)
        lam, gam, pis, lps = self.unpack(z)
        s: Any = x0
        t: Any = 0.0
        res = []
        starts, s_starts, l_starts, costs, s_minus, l_minus, rates = [], [], [], [], [], [], []
        sig = self.unpack_switches(z)
        etas = self.unpack_etas(z)
        switch_res: list[Any] = []
        vs = self.unpack_event_controls(z)
        v_res: list[Any] = []

        def arcs_of(k: int, s: Any, lam: Any, t0: Any, t1: Any) -> tuple[Any, Any, Any]:
            # the phase's arcs, with the switching condition u_unc_i = value at each switch;
            # the entry of a pure state row's boundary arc also needs c_r(s) = 0, and the
            # costate jumps there
            ends = [t0, *sig[k], t1]
            J: Any = 0
            for j in range(len(self.arcs[k])):
                if j:
                    switch_res.append(self.switch_condition(k, j, s, lam))
                    r = self.jump_rows[k][j - 1]
                    if r >= 0:
                        switch_res.append(self.fl.state_fn(s)[0][r])
                        lam = self.entry_jump(k, j - 1, s, lam, etas[k][j - 1])
                s, lam, Jj = phase(k, j, s, lam, ends[j + 1] - ends[j])
                J = Jj if j == 0 else J + Jj
            return s, lam, J

        for k in range(self.K):
            starts.append(t)
            s_starts.append(s)
            l_starts.append(lam)
            sm, lm, J = arcs_of(k, s, lam, t, gam[k])
            costs.append(J)
            # a reset that reads the control: s+ = g(s-, v_k), Dg its Jacobian at v_k
            psi, gpsi, sp, Dg = self.guard_at(k, sm, vs[k])
            lp = lps[k]
            v_res += self.event_control_conditions(k, sm, vs[k], lp)
            before, after = self.law_at(k, -1), self.law_at(k + 1, 0)
            res.append(psi)
            res.append(lm - ca.mtimes(Dg.T, lp) - pis[k] * gpsi)
            res.append(before.H_star(sm, lm) - after.H_star(sp, lp))
            s_minus.append(sm)
            l_minus.append(lm)
            rates.append(ca.dot(gpsi, ocp.f(sm, before.u_star(sm, lm))))
            s, lam, t = sp, lp, gam[k]
        starts.append(t)
        s_starts.append(s)
        l_starts.append(lam)
        sT, lT, J = arcs_of(self.K, s, lam, t, T)
        costs.append(J)
        phiT, gphi = self.phi(sT)
        if self.terminal is None:
            res.insert(0, lT - gphi)
        else:
            # lambda(T) = grad phi - Dh_eq^T nu - Dh_in^T mu (module notes)
            nu, mu = self.unpack_terminal(z)
            h_eq, D_eq, h_in, D_in = self.terminal(sT)
            res.insert(0, lT - gphi + ca.mtimes(D_eq.T, nu) + ca.mtimes(D_in.T, mu))
            res.append(h_eq)
            res.append(fischer_burmeister(mu, h_in))
        H_T = self.law_at(self.K, -1).H_star(sT, lT)
        res += switch_res
        res += v_res
        if self.free:
            res.append(H_T)
        R = ca.vertcat(*res)
        F = ca.Function("hmp_F", [z, x0, T_par, *extra], [R, ca.jacobian(R, z)])
        running = sum(costs[1:], costs[0])
        hc = ca.horzcat
        traj = ca.Function(
            "hmp_traj",
            [z, x0, T_par, *extra],
            [
                hc(*starts),
                hc(*s_starts),
                hc(*l_starts),
                hc(*costs),
                phiT,
                running,
                hc(*s_minus) if s_minus else ca.DM(nx, 0),
                hc(*l_minus) if l_minus else ca.DM(nx, 0),
                hc(*rates) if rates else ca.DM(1, 0),
                sT,
                lT,
                T,
                H_T,
            ],
        )
        return F, traj

    def law_at(self, k: int, j: int) -> Any:
        """The law (``u_star``, ``H_star``) of arc ``j`` of phase ``k``."""
        return self  # disc scenes: one law

    def switch_condition(self, k: int, j: int, s: Any, lam: Any) -> Any:
        """The equation of the switch into arc ``j`` of phase ``k`` at ``(s, lambda)``:
        ``argmin H_i = bound`` for a saturation; on a problem with path constraints the
        free side's ``u*_i = bound``, or ``c_r(s, u*) = 0`` under the law without the row
        (``u`` is continuous at a junction: ``nu_r = 0`` there)."""
        _, i, value = self.switches[k][j - 1]
        fl = getattr(self, "fl", None)
        if fl is None or not fl.m_path:
            return self.u_unc(s, lam)[i] - value
        a = self.arcs[k][j - 1]
        free = self.law_at(k, j - 1) if a[i][0] != a[i][1] else self.law_at(k, j)
        u = free.u_star(s, lam)
        if i < self.nu:
            return u[i] - value
        return fl.c(s, u)[i - self.nu]


class _DiscPieces:
    """Disc scenes: what every sequence of one structure shares (``u*``, ``H``, the guards,
    ``phi``, ``A`` and ``eps``), built once."""

    def __init__(self, ocp: HybridOCP) -> None:
        nx = ocp.nx
        s, lam, u, H, _, u_star = _argmin_hamiltonian(ocp)
        self.u_star = ca.Function("u_star", [s, lam], [u_star])
        self.H = ca.Function("H", [s, lam, u], [H])
        self.H_star = ca.Function("H_star", [s, lam], [ca.substitute(H, u, u_star)])
        self.guards = _disc_guard_fns(ocp, s)
        phi = ocp.phi(s)
        self.phi = ca.Function("phi", [s], [phi, ca.gradient(phi, s)])
        # f = (v, A u) with constant A; L = eps |u|^2
        self.A = np.asarray(ca.DM(ca.jacobian(ocp.f(s, u), u)))[nx // 2 :]
        self.eps = float(ocp.meta["control_weight"])


_DISC_PIECES: weakref.WeakKeyDictionary[Structure, _DiscPieces] = weakref.WeakKeyDictionary()


def _disc_pieces(ocp: HybridOCP) -> _DiscPieces:
    return _built_once(_DISC_PIECES, ocp.structure, lambda: _DiscPieces(ocp))


class _DiscCore(_CoreBase):
    """Disc scenes: the exact polynomial phases of one sequence; its residual and trajectory
    are those of every sequence of its length (:class:`_DiscResidual`) with its guards."""

    def __init__(self, ocp: HybridOCP, sequence: list[str]) -> None:
        super().__init__(ocp, sequence)
        pieces = _disc_pieces(ocp)
        self.u_star, self.H, self.H_star, self.phi = (
            pieces.u_star, pieces.H, pieces.H_star, pieces.phi
        )  # fmt: skip
        self.f = ocp.f
        self.guard_fns = [pieces.guards[j] for j in self.guard_index]
        self.A, self.eps = pieces.A, pieces.eps
        self.terminal = None  # disc scenes have none (is_disc_scene)

    def phase_u(self, s0: Any, c0: Any, c1: Any, h: Any) -> tuple[Any, Any]:
        """State after ``h`` under ``u(tau) = c0 + c1 tau`` and its running cost."""
        return _phase_u(self.A, self.eps, s0, c0, c1, h)

    def control_coeffs(self, lam0: Any) -> tuple[Any, Any]:
        """``u(tau) = c0 + c1 tau`` from the costate at the phase start."""
        n2 = self.nx // 2
        lp, lv = lam0[:n2], lam0[n2:]
        c0 = -ca.mtimes(self.A.T, lv) / (2 * self.eps)
        c1 = ca.mtimes(self.A.T, lp) / (2 * self.eps)
        return c0, c1

    def phase(self, s0: Any, lam0: Any, h: Any) -> tuple[Any, Any, Any]:
        """``(s, lambda, running cost)`` after a phase of length ``h`` under ``u*``."""
        n2 = self.nx // 2
        c0, c1 = self.control_coeffs(lam0)
        s1, J = self.phase_u(s0, c0, c1, h)
        lam1 = ca.vertcat(lam0[:n2], lam0[n2:] - lam0[:n2] * h)
        return s1, lam1, J

    def _build_residual(self, ocp: HybridOCP) -> tuple[Any, Any]:
        shared = _disc_residual(ocp, self.K)
        idx = np.asarray(self.guard_index, dtype=float)
        return (
            _WithGuards(shared.F, shared.F_layout, idx),
            _WithGuards(shared.traj, shared.traj_layout, idx),
        )


class _DiscTemplate(_DiscCore):
    """Disc scenes: the core of every sequence of ``K`` events, event ``k``'s guard chosen by
    the symbol ``idx[k]`` (as in :class:`_DiscNLP`)."""

    def __init__(self, ocp: HybridOCP, K: int) -> None:
        super().__init__(ocp, [g.name for g in ocp.guards][:1] * K)
        self.idx = ca.SX.sym("idx", K)
        self.all_guards = _disc_pieces(ocp).guards

    def guard_at(self, k: int, s: Any, v: Any = None) -> Any:
        if len(self.all_guards) == 1:  # nothing to choose (single-collision)
            return self.all_guards[0](s)
        return _selected_guard(self.all_guards, self.idx[k], s)


class _DiscResidual:
    """Disc scenes: the residual with its Jacobian, ``F(z, x0, T, idx)``, and the trajectory
    function, ``traj(z, x0, T, idx)``, of every sequence of ``K`` events of one structure,
    the guard of event ``k`` being number ``idx[k]``: built once per (structure, ``K``)
    instead of once per sequence (a search solves the Newton systems of dozens of sequences
    of each length; one build takes about as long as the Newton iterations of a screen)."""

    def __init__(self, ocp: HybridOCP, K: int) -> None:
        t = _DiscTemplate(ocp, K)
        self.F, self.traj = t._assemble(
            ocp, lambda k, j, s, lam, h: t.phase(s, lam, h), ca.SX, [t.idx]
        )
        self.F_layout, self.traj_layout = _dense_layout(self.F), _dense_layout(self.traj)


_DISC_RESIDUALS: weakref.WeakKeyDictionary[Structure, dict[int, _DiscResidual]] = (
    weakref.WeakKeyDictionary()
)


def _disc_residual(ocp: HybridOCP, K: int) -> _DiscResidual:
    with _LOCK:
        shared = _DISC_RESIDUALS.setdefault(ocp.structure, {})
    return _built_once(shared, K, lambda: _DiscResidual(ocp, K))


class _WithGuards:
    """A function of :class:`_DiscResidual` as ``fn(z, x0, T)`` of one sequence, its guard
    numbers bound, returning dense numpy arrays: evaluated through CasADi's buffer API
    (bound once per thread), the same virtual machine and the same bits as ``fn(z, x0, T,
    idx)`` without the ``DM`` conversions of that call, which cost more than the evaluation
    of a screen's residual (a structural zero reads 0.0, as in ``np.asarray`` of the ``DM``)."""

    def __init__(self, fn: ca.Function, layout: list[Any], idx: np.ndarray) -> None:
        self.fn, self.layout, self.idx = fn, layout, idx
        self._local = threading.local()

    def _buffers(self) -> tuple[Any, Any, list[np.ndarray], list[np.ndarray]]:
        bound = getattr(self._local, "bound", None)
        if bound is None:
            fn = self.fn
            buf, run = fn.buffer()
            args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
            outs = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
            for i, a in enumerate(args):
                buf.set_arg(i, memoryview(a))
            for i, r in enumerate(outs):
                buf.set_res(i, memoryview(r))
            args[3][...] = self.idx
            bound = self._local.bound = (buf, run, args, outs)
        return bound

    def __call__(self, z: Any, x0: Any, T: Any) -> list[np.ndarray]:
        buf, run, args, outs = self._buffers()
        args[0][...] = np.asarray(z, dtype=float).ravel()
        args[1][...] = np.asarray(x0, dtype=float).ravel()
        args[2][...] = float(T)
        run()
        if buf.ret() != 0:
            raise RuntimeError(f"numerical evaluation of {self.fn.name()!r} failed")
        dense = []
        for r, (shape, where) in zip(outs, self.layout, strict=True):
            if where is None:
                dense.append(r.reshape(shape, order="F").copy())
            else:
                out = np.zeros(shape)
                out[where] = r
                dense.append(out)
        return dense

    def size1_out(self, i: int) -> int:
        return int(self.fn.size1_out(i))


def _dense_layout(fn: ca.Function) -> list[Any]:
    """Per output of ``fn``: its shape and, when it is sparse, the rows and columns of its
    nonzeros in CasADi's order (``None`` when dense)."""
    out = []
    for i in range(fn.n_out()):
        sp = fn.sparsity_out(i)
        where = None
        if not sp.is_dense():
            rows, cols = sp.get_triplet()
            where = (np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp))
        out.append((sp.shape, where))
    return out


class _FlowCore(_CoreBase):
    """Other problems: one (structure, sequence, arcs, steps per arc); the arcs are the
    structure's DOP853 maps of their laws (:class:`_Law`), composed in MX."""

    def __init__(
        self,
        ocp: HybridOCP,
        sequence: list[str],
        levels: tuple[int, ...],
        free: bool = False,
        arcs: Arcs | None = None,
    ) -> None:
        super().__init__(ocp, sequence, free, arcs)
        self.disc = False  # a disc scene with active bounds takes the generic flow
        fl = _flow(ocp)
        self.fl = fl
        self.n_arcs = sum(len(p) for p in self.arcs)
        if len(levels) != self.n_arcs or any(int(n) < 1 for n in levels):
            raise ValueError(f"steps per arc: {self.n_arcs} positive integers, got {levels}")
        self.arc_levels = tuple(int(n) for n in levels)
        # per phase: the steps of its arcs together (the uniform grid of its dense output)
        self.levels = []
        self._arc_index: list[list[int]] = []
        i = 0
        for p in self.arcs:
            self._arc_index.append(list(range(i, i + len(p))))
            self.levels.append(sum(self.arc_levels[i : i + len(p)]))
            i += len(p)
        self.levels = tuple(self.levels)
        self.laws = [[fl.law(m) for m in p] for p in self.arcs]
        # the dense output's law: the problem's clip (the constrained minimum of H with
        # path constraints), right on every arc of a consistent extremal (the
        # unconstrained flow itself without constraints)
        self.flow: Any = fl.law(global_law(ocp)) if ocp.has_bounds or fl.m_path else fl
        self.u_star, self.H, self.H_star, self.f = fl.u_star, fl.H, fl.H_star, fl.f
        self.u_unc = fl.u_unc
        self.rhs, self.polynomial, self.phi = fl.rhs, fl.polynomial, fl.phi
        self.terminal = fl.terminal
        self.guard_fns = [fl.guards[j] for j in self.guard_index]
        self.reset_values = [fl.reset_values[j] for j in self.guard_index]
        self.reset_grads = [fl.reset_grads[j] for j in self.guard_index]

    def law_at(self, k: int, j: int) -> Any:
        return self.laws[k][j]

    def _build_residual(self, ocp: HybridOCP) -> tuple[Any, Any]:
        def phase(k: int, j: int, s: Any, lam: Any, h: Any) -> Any:
            return self.laws[k][j].phase(self.arc_levels[self._arc_index[k][j]])(s, lam, h)

        return self._assemble(ocp, phase, ca.MX)

    def arc_lengths(self, starts: np.ndarray, T: float, switches: Any) -> list[list[float]]:
        """Per phase, the lengths of its arcs."""
        ends = np.append(np.asarray(starts, dtype=float).ravel(), float(T))
        out = []
        for k in range(self.K + 1):
            cuts = [float(ends[k]), *[float(t) for t in switches[k]], float(ends[k + 1])]
            out.append(list(np.diff(cuts)))
        return out

    def switch_values(self, z: np.ndarray) -> list[list[float]]:
        """Per phase, the switch times of ``z`` as floats."""
        return [[float(t) for t in w] for w in self.unpack_switches(np.asarray(z, dtype=float))]

    def eta_values(self, z: np.ndarray) -> list[list[float]]:
        """Per phase and switch, the entry jumps ``eta`` of ``z`` as floats (0 where none)."""
        return [[float(e) for e in w] for w in self.unpack_etas(np.asarray(z, dtype=float))]

    def phase_errors(
        self, z: np.ndarray, x0: np.ndarray, T: float
    ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
        """Per arc, the step-doubling estimate of the error it makes in the cost.

        Returns
        -------
        errors, cost, starts, states, costates
            ``|J_n - J_2n| + |lambda_end| . |s_n - s_2n|`` of each arc from its start (one
            arc per phase without saturation switches), the shooting cost, and the phase
            starts, states and costates.
        """
        out = [np.asarray(x) for x in self.traj(z, x0, T)]
        starts, s0, l0 = out[0].ravel(), out[1], out[2]
        cost = float(out[4].item()) + float(out[5].item())
        lengths = self.arc_lengths(starts, float(out[11].item()), self.switch_values(z))
        etas = self.eta_values(z)
        errors = np.zeros(self.n_arcs)
        for k in range(self.K + 1):
            s, lam = s0[:, k], l0[:, k]
            for j, law in enumerate(self.laws[k]):
                if j:
                    lam = self.entry_jump(k, j - 1, s, lam, etas[k][j - 1])
                i = self._arc_index[k][j]
                n, h = self.arc_levels[i], lengths[k][j]
                a = [np.asarray(v).ravel() for v in law.phase(n)(s, lam, h)]
                b = [np.asarray(v).ravel() for v in law.phase(2 * n)(s, lam, h)]
                errors[i] = abs(float(a[2][0] - b[2][0])) + float(
                    np.abs(b[1]) @ np.abs(a[0] - b[0])
                )
                s, lam = a[0], a[1]
        return errors, cost, starts, s0, l0

    def phase_nodes(
        self,
        states: np.ndarray,
        costates: np.ndarray,
        lengths: list[list[float]],
        counts: Sequence[int],
        etas: Sequence[Sequence[float]] | None = None,
    ) -> list[np.ndarray]:
        """Per phase, ``counts[k] + 1`` equally spaced nodes ``(s, lambda, running cost)``
        from its start state and costate through its arcs (``lengths``): the compiled map
        on a phase of one arc, else DOP853 steps that stop at each switch (where the
        costate jumps by ``etas[k][j]`` at the entry of a pure state row's boundary arc)."""
        out = []
        for k in range(self.K + 1):
            n = int(counts[k])
            laws = self.laws[k]
            if len(laws) == 1:
                out.append(
                    np.asarray(laws[0].nodes(n)(states[k], costates[k], lengths[k][0])).T.copy()
                )
                continue
            h = sum(lengths[k]) / n
            nx = self.nx
            cuts = np.cumsum(lengths[k])[:-1]
            x = np.concatenate([states[k], costates[k], [0.0]])
            rows = [x.copy()]
            t, j = 0.0, 0
            for i in range(1, n + 1):
                target = i * h
                while j < len(cuts) and cuts[j] < target:
                    x = np.asarray(laws[j].step(x, cuts[j] - t)).ravel()
                    if etas is not None:
                        x[nx : 2 * nx] = self.entry_jump(k, j, x[:nx], x[nx : 2 * nx], etas[k][j])
                    t, j = float(cuts[j]), j + 1
                x = np.asarray(laws[j].step(x, target - t)).ravel()
                t = target
                rows.append(x.copy())
            out.append(np.array(rows))
        return out


def _switch_of(a: ArcLaw, b: ArcLaw, k: int, j: int) -> tuple[int, int, float]:
    """``(arc, component, value)`` of the saturation switch from law ``a`` to law ``b``."""
    diff = [i for i, (p, q) in enumerate(zip(a, b, strict=True)) if p != q]
    if len(diff) != 1:
        raise ValueError(f"arcs {j} and {j + 1} of phase {k} must differ in one control")
    i = diff[0]
    p, q = a[i], b[i]
    ends = [m[0] for m in (p, q) if m[0] == m[1]]
    if len(ends) != 1:
        raise ValueError(
            f"phase {k}, control {i}: a switch joins a saturated and a free arc, got {p} -> {q}"
        )
    return j, i, float(ends[0])


class _DiscNLP:
    """Disc scenes: the NLP in event times and linear-in-time phase controls for ``K``
    events, one compiled IPOPT instance per (structure, ``K``). Which guard each event is
    lies in the parameters (one index per event, the guards selected by
    ``if_else``, which also keeps an unselected guard's NaN out), so a search over
    many sequences of one length builds it once."""

    def __init__(self, ocp: HybridOCP, K: int, max_iter: int = 100) -> None:
        nx = ocp.nx
        n2 = nx // 2
        nu = ocp.nu
        s_sym = ca.SX.sym("s", nx)
        u_sym = ca.SX.sym("u", nu)
        self.A = np.asarray(ca.DM(ca.jacobian(ocp.f(s_sym, u_sym), u_sym)))[n2:]
        self.eps = float(ocp.meta["control_weight"])
        guard_fns = _disc_guard_fns(ocp, s_sym)
        phi_s = ocp.phi(s_sym)
        phi_fn = ca.Function("phi", [s_sym], [phi_s, ca.gradient(phi_s, s_sym)])

        w = ca.SX.sym("w", K + (K + 1) * 2 * nu)
        par = ca.SX.sym("p", nx + 1 + K)
        x0, T, idx = par[:nx], par[nx], par[nx + 1 :]
        # the transcription, in one block: phases, guards, approach and time order read
        # together as the NLP's constraints
        gam = [w[k] for k in range(K)]
        C = [w[K + 2 * nu * k : K + 2 * nu * (k + 1)] for k in range(K + 1)]
        s: Any = x0
        t: Any = 0.0
        cost: Any = 0
        g, lbg, ubg = [], [], []
        ends = []  # (s-, s+, u-, u+, grad psi, Dg) per event, for the adjoint
        hs = []
        for k in range(K + 1):
            h = (gam[k] if k < K else T) - t
            hs.append(h)
            c0, c1 = C[k][:nu], C[k][nu:]
            sm, J = _phase_u(self.A, self.eps, s, c0, c1, h)
            cost += J
            if k == K:
                s = sm
                break
            psi, gpsi, sp, Dg = _selected_guard(guard_fns, idx[k], sm)
            g += [psi, ca.dot(gpsi[:n2], sm[n2:])]
            lbg += [0.0, -ca.inf]
            ubg += [0.0, 0.0]
            g.append(gam[k] - (gam[k - 1] if k > 0 else 0.0))
            lbg.append(0.0)
            ubg.append(ca.inf)
            ends.append((sm, sp, c0 + c1 * h, C[k + 1][:nu], gpsi, Dg))
            s, t = sp, gam[k]
        if K:
            g.append(T - gam[K - 1])
            lbg.append(0.0)
            ubg.append(ca.inf)
        phiT, gphi = phi_fn(s)
        cost += phiT
        nlp = {"x": w, "p": par, "f": cost, "g": ca.vertcat(*g) if g else ca.SX(0, 1)}
        self.solver = _compile_disc_nlp(nlp, max_iter)
        self.lbg, self.ubg = lbg, ubg
        self.to_z = _disc_adjoint_fn(ocp, w, par, gphi, gam, hs, ends)


def _disc_guard_fns(ocp: HybridOCP, s_sym: Any) -> list[ca.Function]:
    """Disc scenes: per guard, ``s -> (psi, grad psi, g(s), Dg)``."""
    guard_fns = []
    for j, g in enumerate(ocp.guards):
        psi = g.psi(s_sym)
        gs = g.reset(s_sym)
        guard_fns.append(
            ca.Function(
                f"ev{j}", [s_sym], [psi, ca.gradient(psi, s_sym), gs, ca.jacobian(gs, s_sym)]
            )
        )
    return guard_fns


def _selected_guard(guard_fns: list[ca.Function], index: Any, sm: Any) -> tuple[Any, Any, Any, Any]:
    """Disc scenes: ``(psi, grad psi, g(s), Dg)`` at ``sm`` of guard ``index`` (``if_else``)."""
    parts = [fn(sm) for fn in guard_fns]
    pick = [index == j for j in range(len(guard_fns))]
    return tuple(
        sum(
            (ca.if_else(c, p[m], 0) for c, p in zip(pick, parts, strict=True)),
            ca.SX.zeros(parts[0][m].shape),
        )
        for m in range(4)
    )  # type: ignore[return-value]


def _compile_disc_nlp(nlp: dict[str, Any], max_iter: int) -> ca.Function:
    """Disc scenes: the quiet, tight IPOPT instance of the NLP."""
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.tol": 1e-12,
        "ipopt.acceptable_tol": 1e-9,
        "ipopt.max_iter": max_iter,
    }
    return ca.nlpsol("hmp_nlp", "ipopt", nlp, opts)


def _disc_adjoint_fn(
    ocp: HybridOCP, w: Any, par: Any, gphi: Any, gam: list[Any], hs: list[Any], ends: list[Any]
) -> ca.Function:
    """Disc scenes: ``(w, p) -> z``, the NLP's adjoint costates with the evaluator's jump rule."""
    nx, K = ocp.nx, len(gam)
    n2 = nx // 2
    s_sym, u_sym, lam_sym = ca.SX.sym("s", nx), ca.SX.sym("u", ocp.nu), ca.SX.sym("lam", nx)
    H_fn = ca.Function(
        "H",
        [s_sym, lam_sym, u_sym],
        [ocp.L(s_sym, u_sym) + ca.dot(lam_sym, ocp.f(s_sym, u_sym))],
    )
    # the costate backwards through phases and jumps, in one block (the jump rule)
    lam = gphi
    lps: list[Any] = [None] * K
    pis: list[Any] = [None] * K
    for k in range(K, -1, -1):
        lam = ca.vertcat(lam[:n2], lam[n2:] + lam[:n2] * hs[k])
        if k == 0:
            break
        sm, sp, um, up, gpsi, Dg = ends[k - 1]
        lps[k - 1] = lam
        fm = ocp.f(sm, um)
        Hp = H_fn(sp, lam, up)
        pi = (Hp - ocp.L(sm, um) - ca.dot(lam, ca.mtimes(Dg, fm))) / ca.dot(gpsi, fm)
        pis[k - 1] = pi
        lam = ca.mtimes(Dg.T, lam) + pi * gpsi
    parts = [lam]
    for k in range(K):
        parts += [gam[k], pis[k], lps[k]]
    return ca.Function("nlp_to_z", [w, par], [ca.vertcat(*parts)])


_NLPS: weakref.WeakKeyDictionary[Structure, dict[tuple[int, int], _DiscNLP]] = (
    weakref.WeakKeyDictionary()
)


def _disc_nlp(ocp: HybridOCP, K: int, max_iter: int = 100) -> _DiscNLP:
    nlps = _NLPS.setdefault(ocp.structure, {})
    return _built_once(nlps, (K, max_iter), lambda: _DiscNLP(ocp, K, max_iter))


def _phase_u(A: np.ndarray, eps: float, s0: Any, c0: Any, c1: Any, h: Any) -> tuple[Any, Any]:
    """Disc scenes: state after ``h`` under ``u(tau) = c0 + c1 tau`` and its running cost."""
    n2 = s0.shape[0] // 2
    p0, v0 = s0[:n2], s0[n2:]
    a0 = ca.mtimes(A, c0)
    a1 = ca.mtimes(A, c1)
    p = p0 + v0 * h + a0 * h**2 / 2 + a1 * h**3 / 6
    v = v0 + a0 * h + a1 * h**2 / 2
    J = eps * (ca.sumsqr(c0) * h + ca.dot(c0, c1) * h**2 + ca.sumsqr(c1) * h**3 / 3)
    return ca.vertcat(p, v), J


class ShootingSystem:
    """The HMP system of one event sequence for one problem (its ``x0`` and ``T``).

    Parameters
    ----------
    ocp
        The problem.
    sequence
        Guard names, in event order.
    """

    def __init__(self, ocp: HybridOCP, sequence: list[str], core: Any = None) -> None:
        self.ocp = ocp
        self.core = core if core is not None else _core(ocp, list(sequence), None)
        self.x0 = np.asarray(ocp.x0, dtype=float)
        self.T = float(ocp.horizon)
        """The final time (a free final time's initial guess)."""

    def horizon_of(self, z: np.ndarray) -> float:
        """The final time at ``z`` (its last entry when free, else :attr:`T`)."""
        return float(z[-1]) if self.core.free else self.T

    def fixed_at(self, z: np.ndarray) -> tuple[ShootingSystem, np.ndarray]:
        """A free final time's system and point as the fixed-time system of the problem at
        the final time of ``z`` (``problem.replace(horizon=T)``) and its point: the same
        equations less ``H(T) = 0``. A fixed-time system returns itself."""
        if not self.core.free:
            return self, z
        ocp = self.ocp.replace(horizon=self.horizon_of(z))
        levels, arcs = self._spec()
        core = _core(ocp, self.sequence, levels, False, arcs)
        return ShootingSystem(ocp, self.sequence, core), z[:-1]

    def with_free(self, T: float | None = None) -> ShootingSystem:
        """The free-final-time system of the same sequence and steps (problem at ``T``)."""
        ocp = self.ocp if T is None else self.ocp.replace(horizon=float(T))
        levels, arcs = self._spec()
        return ShootingSystem(ocp, self.sequence, _core(ocp, self.sequence, levels, True, arcs))

    def _spec(self) -> tuple[tuple[int, ...] | None, Arcs | None]:
        """``(steps per arc, arcs)`` that rebuild this system's core (``None`` for disc)."""
        if self.disc:
            return None, None
        return self.core.arc_levels, self.core.arcs

    @property
    def spec(self) -> tuple[tuple[int, ...] | None, Arcs | None]:
        """What :func:`shooting_system` needs besides the problem and the sequence to
        rebuild this system: ``(levels, arcs)`` (``(None, None)`` for a disc scene)."""
        return self._spec()

    def switch_times(self, z: np.ndarray) -> list[list[float]]:
        """Per phase, the saturation switch times of ``z`` (empty lists without them)."""
        return [[float(t) for t in w] for w in self.core.unpack_switches(np.asarray(z, float))]

    def __getattr__(self, name: str) -> Any:
        # the core's compiled pieces (sequence, K, nx, nu, disc, levels, A, eps, guard_fns,
        # u_star, ...)
        if name == "core":
            raise AttributeError(name)
        return getattr(self.core, name)

    def F(self, z: np.ndarray) -> tuple[Any, Any]:
        """Residual and its Jacobian at ``z``."""
        return self.core.F(z, self.x0, self.T)

    def residual(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual and Jacobian as numpy arrays (non-finite on an evaluation failure)."""
        return _residual_and_jacobian(_Bound(self), z)

    def traj(self, z: np.ndarray) -> list[np.ndarray]:
        """Phase starts, states, costates, costs and the end state of a point ``z``
        (:meth:`nodes` then follows its saturation switches)."""
        out = [np.asarray(x) for x in self.core.traj(z, self.x0, self.T)]
        self._switches = self.switch_times(z)
        self._etas = None if self.disc else self.core.eta_values(z)
        return out

    def phase_errors(self, z: np.ndarray) -> tuple[np.ndarray, float]:
        """Per phase, the estimated error the integration makes in the cost (step doubling,
        module notes), and the shooting cost; zeros for disc scenes (exact phases)."""
        if self.disc:
            out = self.traj(z)
            return np.zeros(self.K + 1), float(out[4].item()) + float(out[5].item())
        errors, cost, *_ = self.core.phase_errors(z, self.x0, self.T)
        return errors, cost

    def nodes(
        self,
        starts: np.ndarray,
        states: np.ndarray,
        costates: np.ndarray,
        T: float | None = None,
    ) -> list[np.ndarray]:
        """Generic problems: the nodes ``(n_k + 1, 2 nx + 1)`` of each phase's steps, from the
        phase starts, states and costates (``(K + 1,)``, ``(K + 1, nx)`` twice), up to the
        final time ``T`` (default :attr:`T`)."""
        return self.sample(starts, states, costates, self.core.levels, T)

    def sample(
        self,
        starts: np.ndarray,
        states: np.ndarray,
        costates: np.ndarray,
        counts: Sequence[int],
        T: float | None = None,
        switches: Sequence[Sequence[float]] | None = None,
        etas: Sequence[Sequence[float]] | None = None,
    ) -> list[np.ndarray]:
        """Generic problems: ``counts[k] + 1`` equally spaced nodes of each phase (as
        :meth:`nodes`), through the saturation switches ``switches`` and with the entry
        jumps ``etas`` of pure state rows (default: those of the last :meth:`traj`)."""
        end = self.T if T is None else float(T)
        if switches is None:
            switches = getattr(self, "_switches", None)
            if switches is None or len(switches) != self.K + 1:
                switches = [[]] * (self.K + 1)
        if etas is None and self.core.n_eta:
            etas = getattr(self, "_etas", None)
        lengths = self.core.arc_lengths(starts, end, switches)
        return self.core.phase_nodes(states, costates, lengths, counts, etas)

    @property
    def arc_levels(self) -> tuple[int, ...]:
        """Generic problems: the DOP853 steps of each arc (phase-major)."""
        return self.core.arc_levels

    def with_levels(self, levels: tuple[int, ...]) -> ShootingSystem:
        """The same system with other numbers of steps per arc (generic problems; one arc
        per phase without saturation switches)."""
        core = _core(self.ocp, self.sequence, levels, self.core.free, self.core.arcs)
        return ShootingSystem(self.ocp, self.sequence, core)

    def with_arcs(self, arcs: Arcs, levels: tuple[int, ...] | None = None) -> ShootingSystem:
        """The same sequence and final-time mode with other arcs (generic flow)."""
        core = _core(self.ocp, self.sequence, levels, self.core.free, arcs)
        return ShootingSystem(self.ocp, self.sequence, core)

    def solve_nlp(
        self, gamma0: np.ndarray, coeffs0: np.ndarray, max_iter: int = 100
    ) -> tuple[np.ndarray, bool, float]:
        """Disc scenes: IPOPT on event times and linear-in-time phase controls.

        Returns
        -------
        z, success, infeasibility
            Starting point for Newton on the HMP system (costates of the NLP's control by
            the adjoint with the HMP jump relation), IPOPT's success flag and the largest
            violation of the NLP's constraints (guards, approach, time order) at its point.
        """
        nlp = _disc_nlp(self.ocp, self.K, max_iter)
        solver, lbg, ubg, to_z = nlp.solver, nlp.lbg, nlp.ubg, nlp.to_z
        K, nu = self.K, self.nu
        lbw = [0.0] * K + [-ca.inf] * ((K + 1) * 2 * nu)
        ubw = [self.T] * K + [ca.inf] * ((K + 1) * 2 * nu)
        par = np.concatenate([self.x0, [self.T], self.guard_index])
        w0 = np.concatenate([np.asarray(gamma0, float), np.asarray(coeffs0, float).ravel()])
        sol = solver(x0=w0, p=par, lbg=lbg, ubg=ubg, lbx=lbw, ubx=ubw)
        ok = bool(solver.stats()["success"])
        w = np.asarray(sol["x"]).ravel()
        g = np.asarray(sol["g"], dtype=float).ravel()
        viol = np.maximum(np.asarray(lbg, float) - g, g - np.asarray(ubg, float))
        infeasibility = float(np.max(viol, initial=0.0)) if np.all(np.isfinite(g)) else np.inf
        return np.asarray(to_z(w, par)).ravel(), ok, infeasibility

    def z_from_controls(self, gamma: np.ndarray, coeffs: np.ndarray) -> np.ndarray:
        """Disc scenes: HMP unknowns from event times and linear phase controls (their
        adjoint costates, with the HMP jump rule)."""
        to_z = _disc_nlp(self.ocp, self.K).to_z
        par = np.concatenate([self.x0, [self.T], self.guard_index])
        w = np.concatenate([np.asarray(gamma, float), np.asarray(coeffs, float).ravel()])
        return np.asarray(to_z(w, par)).ravel()


class _Bound:
    """``F(z)`` with the system's data bound (for :func:`_residual_and_jacobian`)."""

    def __init__(self, system: ShootingSystem) -> None:
        self.system = system

    def __call__(self, z: np.ndarray) -> tuple[Any, Any]:
        return self.system.F(z)

    def size1_out(self, i: int) -> int:
        return int(self.system.core.F.size1_out(i))


def _nilpotent_linear(rhs: Any, x: Any) -> bool:
    """Whether ``dx/dt = rhs`` is linear in ``x`` with a constant, nilpotent matrix of index
    at most 4 (then its solution is a cubic polynomial in time)."""
    M = ca.jacobian(rhs, x)
    if ca.depends_on(M, x):
        return False
    try:
        Mn = np.asarray(ca.evalf(M), dtype=float)
    except RuntimeError:
        return False
    P = np.linalg.matrix_power(Mn, 4)
    return bool(np.allclose(P, 0.0, atol=1e-12 * max(1.0, float(np.abs(Mn).max()) ** 4)))


def _core(
    ocp: HybridOCP,
    sequence: list[str],
    levels: Any,
    free: bool | None = None,
    arcs: Arcs | None = None,
) -> Any:
    """The compiled core of ``(structure, sequence)`` (and steps per arc, whether the final
    time is an unknown: default, whether the problem's is free, and the arcs: default one
    per phase under the problem's bounds), shared."""
    # levels name a generic flow: a disc scene's extremal with active bounds (the
    # closed-form phases have no saturation)
    disc = is_disc_scene(ocp) and arcs is None and (levels is None or not ocp.has_bounds)
    free = ocp.free_horizon if free is None else bool(free)
    if not disc:
        if arcs is None:
            arcs = ((global_law(ocp),),) * (len(sequence) + 1)
        width = ocp.nu + path_rows(ocp)
        arcs = tuple(tuple(_full_law(m, width) for m in p) for p in arcs)
        if len(arcs) != len(sequence) + 1:
            raise ValueError(f"arcs: one tuple per phase ({len(sequence) + 1}), got {len(arcs)}")
        if levels is None:
            levels = _LEVELS.get(ocp.structure, {}).get((tuple(sequence), arcs))
        if levels is None:
            fl = _flow(ocp)
            levels = tuple(fl.law(m).start_steps for p in arcs for m in p)
    # the bounds of the resets' own controls enter the compiled conditions (data, not
    # structure: part of the key)
    comps = dict(zip([g.name for g in ocp.guards], reset_controls(ocp), strict=True))
    vkey = None
    if any(comps.get(n) for n in sequence):
        vkey = tuple(tuple(map(float, b)) for b in _reset_bounds(ocp))
    key = (tuple(sequence), None if disc else tuple(int(n) for n in levels), free, arcs, vkey)
    cores = _CORES.setdefault(ocp.structure, {})
    return _built_once(
        cores,
        key,
        lambda: (
            _DiscCore(ocp, list(sequence))
            if disc
            else _FlowCore(ocp, list(sequence), key[1], free, arcs)
        ),
    )


def shooting_system(
    ocp: HybridOCP,
    sequence: list[str],
    levels: tuple[int, ...] | None = None,
    *,
    free: bool | None = None,
    arcs: Arcs | None = None,
) -> ShootingSystem:
    """The system for ``(ocp, sequence)``; the compiled core is shared by every problem with
    the same structure.

    Parameters
    ----------
    ocp, sequence
        The problem and the guard names in event order.
    levels
        Generic problems: DOP853 steps on each of the ``K + 1`` phases; default: those the
        sequence was last accepted at by :func:`refine` (for this structure), else
        :data:`SUBSTEPS_POLYNOMIAL` or :data:`SUBSTEPS` each. Ignored for disc scenes.
    free
        Whether the final time is an unknown (its guess ``ocp.horizon``); default: whether
        ``ocp`` has a free final time. ``False`` on such a problem solves it at
        ``ocp.horizon`` (a final time at its bound, or an extremal already found).
    arcs
        The control law of each arc of each phase (saturation switches
        between arcs as unknowns); ``levels`` then counts steps per arc. Default: one arc
        per phase, ``u* = clip(argmin H, u_min, u_max)`` (``argmin H`` without bounds), and
        a disc scene's closed-form phases.
    """
    core = _core(ocp, list(sequence), levels, free, arcs)
    return ShootingSystem(ocp, list(sequence), core)


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
            _LEVELS.setdefault(S.ocp.structure, {})[tuple(S.sequence), S.core.arcs] = levels
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


# ------------------------------------------------------------------------- saturation
SATURATION_SAMPLES = 128
"""Equally spaced samples per phase on which :func:`detect_arcs` reads ``argmin H`` against
the bounds (an arc shorter than their spacing is found by a later round, when the extremal
of the arcs found shows it)."""
SATURATION_ROUNDS = 6
"""The most active-set rounds of :func:`saturate` (arcs found, extremal solved, checked)."""
SATURATION_TOL = 1e-7
"""How far, relative to ``1 + max |bound|``, ``argmin H`` may lie on the wrong side of a
bound on an arc before the arcs are wrong (rounding at the switches is far below it)."""


def saturation_check(ocp: HybridOCP) -> str | None:
    """``None`` when the reference can take ``u* = clip(argmin H, u_min, u_max)`` (no
    bounds, or a diagonal control weight ``d2H/du2``: then the clip is the box-constrained
    minimum), else the reason."""
    if not ocp.has_bounds or ocp.nu == 1:
        return None
    s, lam, u = ca.SX.sym("s", ocp.nx), ca.SX.sym("lam", ocp.nx), ca.SX.sym("u", ocp.nu)
    Huu = ca.hessian(ocp.L(s, u) + ca.dot(lam, ocp.f(s, u)), u)[0]
    try:
        W = np.asarray(ca.evalf(Huu), dtype=float)
    except RuntimeError:
        return "the control weight d2L/du2 is not a constant matrix"
    if np.any(np.abs(W - np.diag(np.diag(W))) > 1e-14 * np.abs(W).max()):
        return (
            "the reference handles control bounds for a diagonal control weight d2L/du2 only "
            "(then u* = clip(argmin H) is exact); use method 'dt'"
        )
    return None


def _bound_scale(ocp: HybridOCP) -> float:
    assert ocp.u_min is not None and ocp.u_max is not None
    finite = np.concatenate([ocp.u_min[np.isfinite(ocp.u_min)], ocp.u_max[np.isfinite(ocp.u_max)]])
    return 1.0 + float(np.abs(finite).max(initial=0.0))


def _phase_samples(
    S: ShootingSystem, z: np.ndarray, samples: int
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per phase, ``samples + 1`` equally spaced times and the nodes ``(s, lambda, running
    cost)`` there, through the arcs of ``S``."""
    out = S.traj(z)
    starts, s0, l0 = out[0].ravel(), out[1].T, out[2].T
    T = float(out[11].item())
    etas = S.core.eta_values(z) if S.core.n_eta else None
    nodes = S.sample(starts, s0, l0, [samples] * (S.K + 1), T, S.switch_times(z), etas)
    ends = np.append(starts, T)
    times = []
    for k, X in enumerate(nodes):
        n = X.shape[0] - 1
        times.append(ends[k] + (ends[k + 1] - ends[k]) * np.arange(n + 1) / n)
    return times, nodes


def _samples(
    S: ShootingSystem, z: np.ndarray, samples: int
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per phase, sample times and ``argmin H`` there ``(n + 1, nu)``."""
    times, nodes = _phase_samples(S, z, samples)
    fl = _flow(S.ocp)
    nx = S.nx
    U = [np.asarray(fl.u_unc.map(X.shape[0])(X[:, :nx].T, X[:, nx : 2 * nx].T)).T for X in nodes]
    return times, U


def saturation_mismatch(
    S: ShootingSystem, z: np.ndarray, samples: int = SATURATION_SAMPLES
) -> float:
    """The largest inconsistency of ``S``'s arcs at ``z``, relative to ``1 + max |bound|``:
    on a free arc ``argmin H`` outside the bounds, on a saturated arc inside them."""
    ocp = S.ocp
    assert ocp.u_min is not None and ocp.u_max is not None
    times, U = _samples(S, z, samples)
    sw = S.switch_times(z)
    worst = 0.0
    for k in range(S.K + 1):
        arcs = S.core.arcs[k]
        j = np.searchsorted(np.asarray(sw[k]), times[k], side="right")
        for i in range(times[k].size):
            mode = arcs[int(j[i])]
            for c, (lo, hi) in enumerate(mode):
                u = float(U[k][i, c])
                if lo == hi:
                    wrong = (ocp.u_max[c] - u) if lo == ocp.u_max[c] else (u - ocp.u_min[c])
                else:
                    wrong = max(ocp.u_min[c] - u, u - ocp.u_max[c])
                worst = max(worst, wrong)
    return worst / _bound_scale(ocp)


def detect_arcs(
    S: ShootingSystem, z: np.ndarray, samples: int = SATURATION_SAMPLES
) -> tuple[Arcs, list[list[float]]]:
    """The arcs that ``u* = clip(argmin H)`` takes along the extremal ``(S, z)`` and their
    switch times, interpolated linearly between ``samples + 1`` samples per phase."""
    ocp = S.ocp
    if path_rows(ocp):
        arcs, switches, _ = _detect_path_arcs(S, z, samples)
        return arcs, switches
    assert ocp.u_min is not None and ocp.u_max is not None
    lo, hi = ocp.u_min, ocp.u_max
    times, U = _samples(S, z, samples)

    def mode_of(cls: np.ndarray) -> ArcLaw:
        return tuple(
            (-math.inf, math.inf) if c == 0 else (float(hi[i]), float(hi[i]))
            if c > 0 else (float(lo[i]), float(lo[i]))
            for i, c in enumerate(cls)
        )  # fmt: skip

    arcs: list[tuple[ArcLaw, ...]] = []
    switches: list[list[float]] = []
    for t, Uk in zip(times, U, strict=True):
        cls = np.where(Uk > hi, 1, np.where(Uk < lo, -1, 0))
        cur = cls[0].copy()
        modes, sw = [mode_of(cur)], []
        for i in range(1, t.size):
            if np.array_equal(cls[i], cur):
                continue
            events = []
            for c in np.nonzero(cls[i] != cur)[0]:
                a, b = int(cur[c]), int(cls[i][c])
                path = [a, 0, b] if a * b == -1 else [a, b]
                for p, q in zip(path[:-1], path[1:], strict=False):
                    bound = hi[c] if 1 in (p, q) else lo[c]
                    f0, f1 = Uk[i - 1, c] - bound, Uk[i, c] - bound
                    frac = f0 / (f0 - f1) if f0 != f1 else 1.0
                    events.append((t[i - 1] + (t[i] - t[i - 1]) * frac, int(c), q))
            for tt, c, q in sorted(events):
                cur[c] = q
                modes.append(mode_of(cur))
                sw.append(float(tt))
        arcs.append(tuple(modes))
        switches.append(sw)
    return tuple(arcs), switches


def _arc_of_samples(S: ShootingSystem, z: np.ndarray, k: int, t: np.ndarray) -> np.ndarray:
    """The arc of phase ``k`` that holds each time ``t``."""
    return np.searchsorted(np.asarray(S.switch_times(z)[k]), t, side="right")


def _state_values(S: ShootingSystem, X: np.ndarray) -> np.ndarray:
    """``(n, m)``: the pure state rows ``c_r(s)`` at the nodes ``X`` (0 in mixed rows)."""
    fl = _flow(S.ocp)
    return np.asarray(fl.state_fn.map(X.shape[0])(X[:, : S.nx].T)[0], dtype=float).T


def _state_tol(c: np.ndarray) -> float:
    """How far below 0 a pure state row may sample before it counts as violated (relative
    to ``1 + max |c|``: rounding and integration error near a junction, where c is 0 to
    second order)."""
    return SATURATION_TOL * (1.0 + float(np.max(np.abs(c), initial=0.0)))


def _detect_path_arcs(
    S: ShootingSystem, z: np.ndarray, samples: int
) -> tuple[Arcs, list[list[float]], list[list[float]]]:
    """:func:`detect_arcs` with path constraints: the active set of the constrained minimum
    of ``H`` (:func:`global_law`) at each sample, a junction of a row where its function
    (``nu`` where active, ``-c`` elsewhere) changes sign, interpolated linearly; a bound's
    switch at the middle of the samples around it. A pure state row is active where ``S``
    already has it active (the junctions found stay where they are) and where it samples
    below 0 (a boundary arc from where ``c_r`` crosses 0 down to where it crosses back).
    Also per phase and switch the entry jumps ``eta`` to start from (a kept entry's own,
    else 0)."""
    ocp = S.ocp
    nu = ocp.nu
    lo = np.full(nu, -np.inf) if ocp.u_min is None else ocp.u_min
    hi = np.full(nu, np.inf) if ocp.u_max is None else ocp.u_max
    law = _flow(ocp).law(global_law(ocp))
    times, nodes = _phase_samples(S, z, samples)
    nx = S.nx
    pure = state_rows(ocp)
    old_sw = S.switch_times(z)
    old_eta = S.core.eta_values(z) if pure and not S.disc else None

    def mode_of(cls: np.ndarray) -> ArcLaw:
        box = tuple(
            (-math.inf, math.inf) if c == 0 else (float(hi[i]), float(hi[i]))
            if c > 0 else (float(lo[i]), float(lo[i]))
            for i, c in enumerate(cls[:nu])
        )  # fmt: skip
        return box + tuple((0.0, 0.0) if c > 0 else (-math.inf, math.inf) for c in cls[nu:])

    arcs: list[tuple[ArcLaw, ...]] = []
    switches: list[list[float]] = []
    etas: list[list[float]] = []
    for k, (t, X) in enumerate(zip(times, nodes, strict=True)):
        _, cls, sig = (
            np.asarray(v).T for v in law.path_law.map(X.shape[0])(X[:, :nx].T, X[:, nx : 2 * nx].T)
        )
        cls = np.rint(cls).astype(int)
        # a kept junction of a pure state row: (time, row, class after) -> its eta
        kept: dict[tuple[int, int], tuple[float, float, int]] = {}
        if pure:
            cs = _state_values(S, X)
            j = _arc_of_samples(S, z, k, t)
            old = S.core.arcs[k]
            for r in pure:
                held = np.array([old[int(a)][nu + r] == (0.0, 0.0) for a in j])
                cls[:, nu + r] = held | (cs[:, r] < -_state_tol(cs[:, r]))
                sig[:, r] = -cs[:, r]
            for i, (a, b) in enumerate(zip(old[:-1], old[1:], strict=True)):
                for r in pure:
                    if a[nu + r] != b[nu + r]:
                        q = int(b[nu + r] == (0.0, 0.0))
                        e = old_eta[k][i] if old_eta is not None else 0.0
                        kept[(i, r)] = (old_sw[k][i], e, q)
        cur = cls[0].copy()
        modes, sw, ew = [mode_of(cur)], [], []
        for i in range(1, t.size):
            if np.array_equal(cls[i], cur):
                continue
            events = []
            for c in np.nonzero(cls[i] != cur)[0]:
                a, b = int(cur[c]), int(cls[i][c])
                path = [a, 0, b] if a * b == -1 else [a, b]
                frac, eta = 0.5, 0.0
                if c >= nu:
                    f0, f1 = sig[i - 1, c - nu], sig[i, c - nu]
                    if f0 * f1 < 0:
                        frac = f0 / (f0 - f1)
                tt = t[i - 1] + (t[i] - t[i - 1]) * frac
                for (_, r), (t_old, e_old, q) in kept.items():
                    if c == nu + r and q == b and t[i - 1] <= t_old <= t[i]:
                        tt, eta = t_old, e_old
                for q in path[1:]:
                    events.append((tt, int(c), q, eta))
            for tt, c, q, eta in sorted(events):
                cur[c] = q
                modes.append(mode_of(cur))
                sw.append(float(tt))
                ew.append(float(eta))
        arcs.append(tuple(modes))
        switches.append(sw)
        etas.append(ew)
    return tuple(arcs), switches, etas


def arc_mismatch(S: ShootingSystem, z: np.ndarray, samples: int = SATURATION_SAMPLES) -> float:
    """The largest inconsistency of ``S``'s arcs at ``z``: :func:`saturation_mismatch`
    without path constraints; with them, on ``samples + 1`` samples per phase, the largest
    of the arc's control against the constrained minimum of ``H`` (relative to ``1 + max
    |u|``) and of a negative multiplier ``nu`` of an active row (relative to ``1 + max
    |nu|``): zero exactly when each arc's law is the pointwise minimum of ``H`` over the
    constraints with ``nu >= 0``.

    A pure state row ``c_r(s) >= 0`` (its boundary arcs held by ``dc_r/dt = 0``) adds: its
    violation where the arc ignores it (relative to ``1 + max |c_r|``), and on its boundary
    arcs a ``nu_r`` that grows (``-dnu_r/dt`` is the direct adjoining's multiplier, ``>= 0``)
    and a negative entry jump ``eta`` (both relative to ``1 + max |nu|``); the arc's
    control is compared with the constrained minimum of ``H`` with the row held as the arc
    holds it."""
    ocp = S.ocp
    if not path_rows(ocp):
        return saturation_mismatch(S, z, samples) if ocp.has_bounds else 0.0
    fl = _flow(ocp)
    nu = ocp.nu
    pure = state_rows(ocp)
    glob_mode = global_law(ocp)

    def reference(mode: ArcLaw) -> _Law:
        # the pointwise minimum with each pure state row held as the arc holds it
        return fl.law(
            tuple(mode[i] if i >= nu and i - nu in pure else m for i, m in enumerate(glob_mode))
        )

    times, nodes = _phase_samples(S, z, samples)
    nx = S.nx
    du, neg, u_max, nu_max, c_neg, grow = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for k, (t, X) in enumerate(zip(times, nodes, strict=True)):
        j = _arc_of_samples(S, z, k, t)
        cs = _state_values(S, X) if pure else None
        prev: np.ndarray | None = None
        for i in range(t.size):
            s, lam = X[i, :nx], X[i, nx : 2 * nx]
            law = S.core.laws[k][int(j[i])]
            ua = np.asarray(law.u_star(s, lam)).ravel()
            ug = np.asarray(reference(law.mode).u_star(s, lam)).ravel()
            nus = np.asarray(law.path_law(s, lam)[0]).ravel()
            du = max(du, float(np.max(np.abs(ua - ug))))
            u_max = max(u_max, float(np.max(np.abs(ug))))
            nu_max = max(nu_max, float(np.max(np.abs(nus), initial=0.0)))
            neg = max(neg, float(np.max(-nus, initial=0.0)))
            if cs is None:
                continue
            for r in pure:
                if law.mode[nu + r] != (0.0, 0.0):
                    c_neg = max(c_neg, -float(cs[i, r]) / (1.0 + float(np.abs(cs[:, r]).max())))
                elif prev is not None and j[i] == j[i - 1]:
                    grow = max(grow, float(nus[r] - prev[r]))
            prev = nus
    eta_neg = 0.0
    if pure:
        eta_neg = max((-e for w in S.core.eta_values(z) for e in w), default=0.0)
    return max(du / (1.0 + u_max), (max(neg, grow, eta_neg)) / (1.0 + nu_max), c_neg)


def path_multipliers(
    S: ShootingSystem, z: np.ndarray, samples: int = SATURATION_SAMPLES
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per phase, ``samples + 1`` times and the path constraints' multipliers ``nu`` there
    ``(samples + 1, m)``, under each arc's own law (0 where a row is not active)."""
    times, nodes = _phase_samples(S, z, samples)
    nx = S.nx
    out = []
    for k, (t, X) in enumerate(zip(times, nodes, strict=True)):
        j = _arc_of_samples(S, z, k, t)
        rows = [
            np.asarray(S.core.laws[k][int(j[i])].path_law(X[i, :nx], X[i, nx : 2 * nx])[0]).ravel()
            for i in range(t.size)
        ]
        out.append(np.array(rows))
    return times, out


def saturate(
    S: ShootingSystem, nr: NewtonResult, *, tol: float = 1e-10, verbose: bool = False
) -> tuple[ShootingSystem, NewtonResult, str]:
    """The extremal with control bounds from a converged point of a system without
    saturation switches (``u* = clip(argmin H)`` on one arc per phase, or a disc scene's
    unconstrained phases).

    An active-set loop: the arcs where ``argmin H`` lies beyond a bound are read off the
    extremal (:func:`detect_arcs`), each saturation switch becomes an unknown time with
    ``argmin H_i = bound`` as its equation, Newton solves the system of those arcs, and
    the arcs are checked against ``argmin H`` along the new extremal
    (:func:`saturation_mismatch`); at most :data:`SATURATION_ROUNDS` rounds. Within each arc
    the law is smooth, so the DOP853 steps keep their order.

    Returns
    -------
    system, newton, reason
        The system of the arcs found and Newton's point on it; ``reason`` is empty unless
        no consistent arcs were found. Without bounds, or a disc scene's extremal inside
        them, the input.
    """
    ocp = S.ocp
    if not (ocp.has_bounds or path_rows(ocp)):
        return S, nr, ""
    if S.disc:
        if ocp.bound_violation(_disc_control_range(S, nr.z)) <= 0.0:
            return S, nr, ""
        clip = ((clip_mode(ocp),),) * (S.K + 1)
        S = S.with_arcs(clip)
        nr = newton(S, nr.z, tol=tol, verbose=verbose)
        if not nr.converged:
            return S, nr, f"Newton with the clipped control: residual {nr.residual:.2e}"
    seen: set[Arcs] = set()
    pure = bool(state_rows(ocp))
    for _ in range(SATURATION_ROUNDS):
        etas = None
        if path_rows(ocp):
            arcs, switches, etas = _detect_path_arcs(S, nr.z, SATURATION_SAMPLES)
        else:
            arcs, switches = detect_arcs(S, nr.z)
        if arcs == S.core.arcs:
            # a pure state row's arcs are kept as they are: their signs decide
            why = _state_signs(S, nr.z) if pure else ""
            return S, nr, why
        if arcs in seen:
            return S, nr, "the arcs cycle between patterns"
        seen.add(arcs)
        new = S.with_arcs(arcs)
        z0 = new.core.with_switches(S.core.strip_switches(nr.z), switches, etas)
        if verbose:
            print(f"  saturation {S.sequence}: arcs {_arcs_text(arcs, ocp.nu)}", file=sys.stderr)
        nr_new = newton(new, z0, tol=tol, verbose=verbose)
        if not nr_new.converged:
            return (
                new,
                nr_new,
                f"Newton on the arcs {_arcs_text(arcs, ocp.nu)}: residual {nr_new.residual:.2e}"
                + _touch_hint(new, nr_new.z),
            )
        bad = _touch_point(new, nr_new.z) or _switch_order(new, nr_new.z)
        if bad:
            return new, nr_new, bad
        S, nr = new, nr_new
        if arc_mismatch(S, nr.z) <= SATURATION_TOL:
            return S, nr, ""
    return S, nr, f"no consistent arcs after {SATURATION_ROUNDS} rounds"


TOUCH_TOL = 1e-6
"""A boundary arc of a pure state row shorter than this fraction of the horizon is a touch
point (the constraint met at one instant), which the reference does not model."""


def _boundary_arcs(S: ShootingSystem, z: np.ndarray) -> list[tuple[int, int, float, float]]:
    """``(phase, row, entry, exit)`` of every boundary arc of a pure state row at ``z`` (its
    phase's start or end where it has no junction there)."""
    pure = state_rows(S.ocp)
    if not pure or S.disc:
        return []
    nu = S.nu
    starts = S.traj(z)[0].ravel()
    ends = np.append(starts, S.horizon_of(z))
    out = []
    for k, (p, w) in enumerate(zip(S.core.arcs, S.switch_times(z), strict=True)):
        cuts = [float(ends[k]), *w, float(ends[k + 1])]
        for r in pure:
            j = 0
            while j < len(p):
                if p[j][nu + r] != (0.0, 0.0):
                    j += 1
                    continue
                first = j
                while j < len(p) and p[j][nu + r] == (0.0, 0.0):
                    j += 1
                out.append((k, r, cuts[first], cuts[j]))
    return out


def _touch_point(S: ShootingSystem, z: np.ndarray) -> str:
    """The reason a converged point is a touch point rather than an arc (a pure state
    row's boundary arc shorter than :data:`TOUCH_TOL` of the horizon, or turned around:
    its exit before its entry, as where the row is met only at an event), else empty."""
    T = S.horizon_of(z)
    for _, r, a, b in _boundary_arcs(S, z):
        if b - a < 0:
            where = f"between t = {b:.6g} and {a:.6g}"
            return _touch_text(r, where, "its boundary arc's exit comes before its entry")
        if b - a < TOUCH_TOL * T:
            return _touch_text(r, f"at t = {a:.6g}", f"its boundary arc shrinks to {b - a:.2g}")
    return ""


def _touch_hint(S: ShootingSystem, z: np.ndarray) -> str:
    """Where Newton failed on arcs with a pure state row's boundary arc whose exit came
    before its entry (a touch point rather than an arc), the words that say so."""
    for _, r, a, b in _boundary_arcs(S, z):
        if np.isfinite(a) and np.isfinite(b) and b < a:
            return (
                f"; pure state row {r}'s boundary arc turned around (exit {b:.6g} before "
                f"entry {a:.6g}): the constraint may be touched at one instant only, a touch "
                "point, which the reference does not model; use method 'dt'"
            )
    return ""


def _touch_text(r: int, where: str, how: str) -> str:
    return (
        f"pure state constraint row {r} is touched at one instant {where} ({how}): a touch "
        "point, not a boundary arc; the reference does not model touch points (a costate "
        "jump without an arc); use method 'dt'"
    )


def _state_signs(S: ShootingSystem, z: np.ndarray) -> str:
    """Empty when the pure state rows' boundary arcs have the multipliers' signs of a
    minimum (``nu >= 0`` and not growing on the arc, ``eta >= 0`` at its entry) and the
    rows hold off them; else which does not (:func:`arc_mismatch`)."""
    bad = arc_mismatch(S, z)
    if bad <= SATURATION_TOL:
        return ""
    return (
        f"the boundary arcs of the pure state constraints do not have the multipliers of a "
        f"minimum (nu >= 0 non-increasing on each arc, eta >= 0 at its entry, c >= 0 off it): "
        f"mismatch {bad:.2e} relative"
    )


def _switch_order(S: ShootingSystem, z: np.ndarray) -> str:
    """Empty when every switch lies inside its phase, in order; else why not."""
    starts = S.traj(z)[0].ravel()
    ends = np.append(starts, S.horizon_of(z))
    for k, w in enumerate(S.switch_times(z)):
        cuts = np.array([ends[k], *w, ends[k + 1]])
        if np.any(np.diff(cuts) < 0):
            return f"switches {w} (saturations, junctions) not in order inside phase {k}"
    return ""


def _arcs_text(arcs: Arcs, nu: int) -> str:
    def one(m: ArcLaw) -> str:
        box = ["free" if lo != hi else f"{lo:g}" for lo, hi in m[:nu]]
        rows = [f"c{r} = 0" for r, (lo, hi) in enumerate(m[nu:]) if lo == hi]
        return "(" + ", ".join(box + rows) + ")"

    return "; ".join(" ".join(one(m) for m in p) for p in arcs)


def _disc_control_range(S: ShootingSystem, z: np.ndarray) -> np.ndarray:
    """Disc scenes: ``u`` at both ends of every phase (linear in time: its extremes)."""
    out = S.traj(z)
    starts, l0 = out[0].ravel(), out[2]
    ends = np.append(starts, S.horizon_of(z))
    rows = []
    for k in range(S.K + 1):
        c0, c1 = (np.asarray(c).ravel() for c in S.core.control_coeffs(l0[:, k]))
        rows += [c0, c0 + c1 * (ends[k + 1] - ends[k])]
    return np.array(rows)
