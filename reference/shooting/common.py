"""What the shooting's parts share: the caches, the problem checks (a Hamiltonian the
reference can minimise in closed form, path constraints and resets it can take), the arcs'
control laws (:data:`ArcLaw`) and the symbolic pieces of ``argmin H`` and the terminal
conditions."""

from __future__ import annotations

import math
import threading
import weakref
from collections.abc import Callable, MutableMapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

import casadi as ca
import numpy as np

from hybridoc.ocp import HybridOCP, Structure

# the steps per phase each sequence was last accepted at, per structure (where the next
# solve of the same sequence starts)
LEVELS: weakref.WeakKeyDictionary[Structure, dict[tuple[str, ...], tuple[int, ...]]] = (
    weakref.WeakKeyDictionary()
)
LOCK = threading.RLock()
_T = TypeVar("_T")


def built_once(cache: MutableMapping[Any, _T], key: Any, build: Callable[[], _T]) -> _T:
    """``cache[key]``, built by ``build()`` once even when threads ask at the same time
    (the cheap lookup first, the build under the lock)."""
    value = cache.get(key)
    if value is None:
        with LOCK:
            value = cache.get(key)
            if value is None:
                value = cache[key] = build()
    return value


def has_closed_form_phases(ocp: HybridOCP) -> bool:
    """Whether the reference takes ``ocp``'s closed-form polynomial phases: the problem offers
    a :class:`~hybridoc.capabilities.LinearControlFlow` (``f = (v, A u)``, ``L = eps |u|^2``;
    a compiled disc scene does) and has no terminal constraints, free final time, path
    constraints or reset that depends on the control (those take the generic flow, whose
    phases are exact for this polynomial flow too: one DOP853 step each)."""
    return ocp.capabilities.flow is not None and not (
        ocp.has_terminal_constraints
        or ocp.free_horizon
        or ocp.path is not None
        or any(g.uses_control for g in ocp.guards)
    )


def is_disc_scene(ocp: HybridOCP) -> bool:
    """Deprecated alias of :func:`has_closed_form_phases` (the test asks for the problem's
    closed-form flow, not for its type)."""
    return has_closed_form_phases(ocp)


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


def checked_hamiltonian(ocp: HybridOCP) -> str | None:
    """:func:`hamiltonian_check`, once per structure."""
    if ocp.structure not in _CHECKED:
        _CHECKED[ocp.structure] = hamiltonian_check(ocp)
    return _CHECKED[ocp.structure]


def residual_and_jacobian(F: Any, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    if ca.depends_on(ca.jacobian(effective_rows(c, s, u, f), u), u):
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


def effective_rows(c: Any, s: Any, u: Any, f: Any) -> Any:
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

    return built_once(_STATE_ROWS, ocp.structure, build)


_STATE_ROWS: weakref.WeakKeyDictionary[Structure, tuple[int, ...]] = weakref.WeakKeyDictionary()


def full_law(mode: ArcLaw, width: int) -> ArcLaw:
    """``mode`` as floats, with an ignored entry for each path constraint it leaves out."""
    mode = tuple((float(lo), float(hi)) for lo, hi in mode)
    return mode + ((-math.inf, math.inf),) * (width - len(mode))


def terminal_fn(ocp: HybridOCP, s: Any) -> ca.Function | None:
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


def argmin_hamiltonian(ocp: HybridOCP) -> tuple[Any, Any, Any, Any, Any, Any]:
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
    return built_once(_RESET_CONTROLS, ocp.structure, build)


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


def reset_bounds(ocp: HybridOCP) -> tuple[np.ndarray, np.ndarray]:
    """The control bounds as two ``(nu,)`` arrays (infinite where there are none)."""
    lo = np.full(ocp.nu, -np.inf) if ocp.u_min is None else np.asarray(ocp.u_min, dtype=float)
    hi = np.full(ocp.nu, np.inf) if ocp.u_max is None else np.asarray(ocp.u_max, dtype=float)
    return lo, hi


def switch_of(a: ArcLaw, b: ArcLaw, k: int, j: int) -> tuple[int, int, float]:
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
