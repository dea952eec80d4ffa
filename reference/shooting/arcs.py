"""Saturation arcs and path-constraint arcs: detecting them along an extremal
(:func:`detect_arcs`), the active-set loop (:func:`saturate`), their consistency
(:func:`arc_mismatch`) and the touch points the reference refuses."""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from hybridoc import tolerances
from hybridoc.ocp import HybridOCP
from hybridoc.reference.shooting.common import (
    ArcLaw,
    Arcs,
    NewtonResult,
    clip_mode,
    global_law,
    path_rows,
    state_rows,
)
from hybridoc.reference.shooting.flow import Law, flow_of
from hybridoc.reference.shooting.refinement import newton

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.reference.shooting.system import ShootingSystem


# ------------------------------------------------------------------------- saturation
SATURATION_SAMPLES = 128
"""Equally spaced samples per phase on which :func:`detect_arcs` reads ``argmin H`` against
the bounds (an arc shorter than their spacing is found by a later round, when the extremal
of the arcs found shows it)."""
SATURATION_ROUNDS = 6
"""The most active-set rounds of :func:`saturate` (arcs found, extremal solved, checked)."""
SATURATION_TOL = tolerances.value("saturation")
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
    fl = flow_of(S.ocp)
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
    fl = flow_of(S.ocp)
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
    law = flow_of(ocp).law(global_law(ocp))
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
    fl = flow_of(ocp)
    nu = ocp.nu
    pure = state_rows(ocp)
    glob_mode = global_law(ocp)

    def reference(mode: ArcLaw) -> Law:
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


TOUCH_TOL = tolerances.value("touch")
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
