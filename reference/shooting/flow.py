"""The generic state-costate flow: each arc's control law ``u*`` (free, clipped, saturated or
held on a path constraint, :class:`Law`) and its phases by fixed DOP853 steps
(:func:`dop853_step`), shared by every sequence of one problem structure (:class:`_Flow`)."""

from __future__ import annotations

import itertools
import math
import weakref
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.ocp import HybridOCP, Structure
from hybridoc.reference import dop853 as tab
from hybridoc.reference.shooting.common import (
    LOCK,
    ArcLaw,
    argmin_hamiltonian,
    built_once,
    effective_rows,
    free_mode,
    full_law,
    path_rows,
    state_rows,
    terminal_fn,
)

SUBSTEPS_POLYNOMIAL = 1
"""DOP853 steps per phase for linear nilpotent state-costate systems (exact)."""
SUBSTEPS = 4
"""DOP853 steps per phase that other problems start from (:func:`refine` adds more)."""
_FLOWS: weakref.WeakKeyDictionary[Structure, _Flow] = weakref.WeakKeyDictionary()


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


class Law:
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
            with LOCK:
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
    ``phi`` and a :class:`Law` per control law met (the unconstrained one's attributes are
    the flow's own: ``u_star``, ``H_star``, ``rhs``, ``step``, ``dense``, ``phase(n)``, ...)."""

    def __init__(self, ocp: HybridOCP) -> None:
        nx, nu = ocp.nx, ocp.nu
        self.nx, self.nu = nx, nu
        s, lam, u, H, Huu, u_star = argmin_hamiltonian(ocp)
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
            c = effective_rows(raw, s, u, ocp.f(s, u))
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
        self._laws: dict[ArcLaw, Law] = {}
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
        self.terminal = terminal_fn(ocp, s)

    def law(self, mode: ArcLaw) -> Law:
        """The :class:`Law` of ``mode``, built once (a law of the controls alone, on a
        problem with path constraints, ignores them)."""
        mode = full_law(mode, self.nu + self.m_path)
        return built_once(self._laws, mode, lambda: Law(self, mode))


def _law_rows(
    fl: _Flow, mode: ArcLaw
) -> tuple[list[tuple[Any, Any, str, int, int]], list[tuple[Any, Any, str, int, int]]]:
    """The rows of a law with path constraints (:func:`_constrained_minimum`), held as
    equalities and as inequalities: ``(C (1, nu), d, kind, index, side)``, kind ``"u"`` (a
    control at a value) or ``"c"`` (a path constraint)."""
    nu = fl.nu
    a, B = fl.c_a, fl.c_B
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
    return eq, ineq


def _active_subsets(
    nu: int, eq: list[tuple[Any, Any, str, int, int]], ineq: list[tuple[Any, Any, str, int, int]]
) -> list[tuple[int, ...]]:
    """The sets of inequality rows (indices into ``ineq``) that may be active together
    beside the equalities ``eq``: at most the controls' room left, one bound per control."""
    room = nu - len(eq)
    subsets: list[tuple[int, ...]] = [()]
    for k in range(1, max(room, 0) + 1):
        for sub in itertools.combinations(range(len(ineq)), k):
            comps = [ineq[j][3] for j in sub if ineq[j][2] == "u"]
            if len(comps) == len(set(comps)):
                subsets.append(sub)
    return subsets


def _constrained_minimum(fl: _Flow, mode: ArcLaw) -> tuple[Any, Any, Any, Any]:
    """``u*``, the path multipliers ``nu``, the classes and the junction functions of a law
    with path constraints (:class:`Law`), in closed form.

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
    eq, ineq = _law_rows(fl, mode)
    subsets = _active_subsets(nu, eq, ineq)

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


def flow_of(ocp: HybridOCP) -> _Flow:
    return built_once(_FLOWS, ocp.structure, lambda: _Flow(ocp))


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
