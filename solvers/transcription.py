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
"""

from __future__ import annotations

import bisect
import dataclasses
import inspect
import math
import signal
import sys
import time
import weakref
from collections.abc import Callable, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from math import comb
from typing import Any

import casadi as ca
import numpy as np

from hybridoc import tolerances
from hybridoc.errors import (
    ConvergenceError,
    EvaluationError,
    HybridocError,
    OptionError,
    SceneError,
    SimultaneousEventError,
)
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate
from hybridoc.methods import Method, option, positive_float, settings_lines
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.progress import NullProgress, Progress, ProgressLike, progress_scope
from hybridoc.solution import Solution, Status, lagrange_pieces
from hybridoc.solvers.threads import flag_interrupts

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

_DEFAULT_MESH = 4
MAX_DEGREE = 9
"""The highest collocation degree: CasADi's Radau tables (``collocation_points``) stop at 9."""
MAX_MESH = 1000
"""The most collocation elements per phase (250 times the default): a typo such as
``--mesh 100000000`` fails with one line instead of building an NLP that fills the memory."""
MAX_NLP_SIZE = 100_000
"""The most variables plus constraints of one transcribed NLP, estimated before it is built
(:func:`nlp_size`). IPOPT's iterations grow faster than the NLP: measured on 2 cores, 13
discs (78 disc pairs, each kept apart at every node), one phase: 11 224 -> 0.13 s per
iteration (500 iterations in 63 s); 44 344 -> 5.6 s to build and more than 290 s in IPOPT.
Problems of the documentation and tests stay under 20 000. Beyond this bound a solve would
run for hours: reduce ``mesh``, the events (``sequence``, another initial guess) or the
bodies."""
_MAX_ITER = 500  # IPOPT iterations per candidate NLP
_BOUND_TOL = tolerances.FEASIBILITY  # judged control-bound violation: INFEASIBLE above it
_PATH_TOL = tolerances.PATH  # judged path-constraint violation: INFEASIBLE above it
_NEAR_MISS = 1e-3  # event-time mismatch (relative to T) that a finer mesh may fix
_GUESS_PERTURBATIONS = 3  # perturbed retries of a guess with simultaneous events
_TERMINAL_REFINEMENTS = 4  # mesh doublings (default mesh 4 -> up to 64) for terminal constraints
_NEAR_MISS_REFINEMENTS = 3  # mesh doublings (default mesh 4 -> up to 32) for a near miss
_CHEAPER_RTOL = tolerances.CHEAPER  # a known control cheaper by more: the result is not-optimal
TERMINAL_TOL = tolerances.TERMINAL  # the default judged terminal-constraint violation
REFINE_RTOL = tolerances.value("refine")
"""The default mesh is refined until the judged cost of the transcription's control and the
NLP's objective agree within ``REFINE_RTOL * max(1, |J|)`` and, on the first mesh, the
collocation defects between the collocation points stay within :data:`DEFECT_TOL`, or after
a refinement the judged costs of the last two meshes agree within the same
(``info["error_estimate"]``)."""
DEFECT_TOL = tolerances.value("defect")
"""The largest collocation defect between collocation points that the default mesh accepts:
``h_e |x'(t_m) - f(x(t_m), u(t_m))|`` at the midpoints ``t_m`` of consecutive nodes of each
element, relative to ``max(1, max |x_i|)`` on the phase (the state's local error over one
element)."""
MAX_ADAPTIVE_MESH = 256
"""The most elements per phase the error-driven refinement of the default mesh reaches (the
default's 4 elements doubled six times); past it, or past :data:`MAX_NLP_SIZE`, a result
whose error estimate is still above the tolerances is ``not-converged``."""
_MAX_ADAPTIONS = 12  # refinements of one candidate
_NLPS: weakref.WeakKeyDictionary[HybridOCP, dict[Any, Any]] = weakref.WeakKeyDictionary()
_GUARD_SCALES: weakref.WeakKeyDictionary[HybridOCP, np.ndarray] = weakref.WeakKeyDictionary()


# ----------------------------------------------------------------------------------------
# collocation tables


@dataclass(frozen=True)
class _Radau:
    """Radau IIA tables on ``[0, 1]`` for degree ``d``."""

    tau: np.ndarray  # (d + 1,): 0 and the d Radau points (the last is 1)
    D: np.ndarray  # (d + 1, d): D[r, j] = dP_r/dtau at Radau point j
    w: np.ndarray  # (d,): Radau quadrature weights
    bernstein: np.ndarray  # (d, d): Bernstein coefficients of the control polynomial

    @classmethod
    def make(cls, d: int) -> _Radau:
        pts = np.array(ca.collocation_points(d, "radau"), dtype=float)
        tau = np.concatenate([[0.0], pts])
        D = np.zeros((d + 1, d))
        for r in range(d + 1):
            others = np.delete(tau, r)
            poly = np.poly1d(others, r=True) / np.prod(tau[r] - others)
            D[r] = np.polyder(poly)(pts)
        w = np.zeros(d)
        for j in range(d):
            others = np.delete(pts, j)
            poly = np.poly1d(others, r=True) / np.prod(pts[j] - others)
            w[j] = np.polyint(poly)(1.0)
        # the control polynomial of degree n = d - 1 through the Radau points: monomial
        # coefficients a = V^-1 u, Bernstein coefficients b_i = sum_k<=i C(i,k)/C(n,k) a_k
        n = d - 1
        to_bern = np.array(
            [[comb(i, k) / comb(n, k) if k <= i else 0.0 for k in range(d)] for i in range(d)]
        )
        bernstein = to_bern @ np.linalg.inv(np.vander(pts, d, increasing=True))
        return cls(tau=tau, D=D, w=w, bernstein=bernstein)

    def control_basis(self, s: np.ndarray) -> np.ndarray:
        """Lagrange basis through the Radau points evaluated at ``s``: shape (len(s), d)."""
        return _lagrange_basis(self.tau[1:], s)


# ----------------------------------------------------------------------------------------
# the NLP for one sequence


class _Constraints:
    """The constraints ``g`` of an NLP as they are added, with their bounds and, per name,
    the slices of ``g`` they occupy (to read their multipliers)."""

    def __init__(self) -> None:
        self.exprs: list[Any] = []
        self.lbg: list[np.ndarray] = []
        self.ubg: list[np.ndarray] = []
        self.index: dict[str, Any] = {}
        self.scale: dict[str, list[np.ndarray]] = {}
        self.n = 0

    def add(
        self,
        name: str,
        expr: Any,
        lo: float | np.ndarray,
        hi: float | np.ndarray,
        scale: float | np.ndarray = 1.0,
    ) -> None:
        """Add the rows ``expr`` (already divided by ``scale``, per row or one number: the
        physical rows are ``scale * expr``, what :meth:`_PhaseNLP.mult` unscales by)."""
        expr = ca.vec(expr)
        m = expr.size1()
        self.exprs.append(expr)
        self.lbg.append(np.broadcast_to(np.asarray(lo, dtype=float), (m,)).copy())
        self.ubg.append(np.broadcast_to(np.asarray(hi, dtype=float), (m,)).copy())
        self.index.setdefault(name, []).append(slice(self.n, self.n + m))
        self.scale.setdefault(name, []).append(
            np.broadcast_to(np.asarray(scale, dtype=float), (m,)).copy()
        )
        self.n += m


class _PhaseNLP:
    """The transcribed NLP of one event sequence (built once, reused for warm starts)."""

    def __init__(
        self,
        ocp: HybridOCP,
        guards: Sequence[int],
        degree: int,
        mesh: Sequence[int],
        fractions: Sequence[np.ndarray | None] | None = None,
    ):
        self.ocp = ocp
        self.guards = list(guards)
        self.d = degree
        self.mesh = list(mesh)
        # per phase: the elements' shares of the phase duration (None: M equal elements)
        self.fractions: list[np.ndarray | None] = (
            [None] * len(self.mesh) if fractions is None else list(fractions)
        )
        self.rad = _Radau.make(degree)
        nx, nu, d = ocp.nx, ocp.nu, degree
        P = len(self.guards) + 1
        self.P = P
        sym = self._symbol_type(ocp)
        self.sym = sym
        # the NLP's own units (module notes, "Units"): the variables are the scaled states
        # (s - s0) / sigma_s, controls u / sigma_u and durations h / sigma_t, the objective
        # J / sigma_J, and every constraint row is divided by its own scale; where the
        # scales are the identity nothing is scaled (the NLP of before, bit for bit)
        sc = ocp.scales
        self.scaled = not sc.is_identity
        self.sx, self.off, self.su = sc.state_array, sc.offset_array, sc.control_array
        self.ts, self.cs = float(sc.time), float(sc.cost)
        self.gs = _guard_scales(ocp)

        h = sym.sym("h", P)
        Xs, Us = [], []
        for k in range(P):
            Xs.append(sym.sym(f"X{k}", nx, self.mesh[k] * d + 1))
            Us.append(sym.sym(f"U{k}", nu, self.mesh[k] * d))
        # the events whose reset depends on the control: each reads its own control v_k, a
        # decision of the NLP (an instant carries no running cost), stored after the U
        self.reset_events = [k for k, gi in enumerate(self.guards) if ocp.guards[gi].uses_control]
        V = sym.sym("V", nu, len(self.reset_events))
        self.V_sym = V
        w_all = ca.vertcat(h, *[ca.vec(X) for X in Xs], *[ca.vec(U) for U in Us], ca.vec(V))
        self.n_w = w_all.size1()

        cons = _Constraints()
        # the final time: fixed, or free in its bounds (the phase durations scale with it)
        T_lo, T_hi = _horizon_range(ocp)
        ts = self.ts
        if self.scaled:
            cons.add("sum_h", ca.sum1(h), T_lo / ts, T_hi / ts, ts)
            x0 = sc.to_scaled_state(ocp.x0)
        else:
            cons.add("sum_h", ca.sum1(h), T_lo, T_hi)
            x0 = ocp.x0
        cons.add("x0", Xs[0][:, 0] - ca.DM(x0), 0.0, 0.0, self.sx)
        cost = 0
        for k in range(P):
            hk = h[k] * ts if self.scaled else h[k]  # the physical duration
            cost = self._add_phase(cons, cost, k, hk, Xs[k], Us[k])
            if k < P - 1:
                self._add_event(cons, k, Xs[k], Us[k], Xs[k + 1])
        s_T = self._phys_x(Xs[-1][:, -1])
        cost = cost + ocp.phi(s_T)
        if self.scaled:
            cost = cost / self.cs
        if ocp.terminal_eq is not None:
            cons.add("terminal_eq", ocp.terminal_eq(s_T), 0.0, 0.0)
        if ocp.terminal_ineq is not None:
            cons.add("terminal_ineq", ocp.terminal_ineq(s_T), 0.0, np.inf)

        self.cost_fn = ca.Function("J", [w_all], [cost])
        self._nlp = {"x": w_all, "f": cost, "g": ca.vertcat(*cons.exprs)}
        self.g_index = cons.index
        self.g_scale = cons.scale
        self.lbg = np.concatenate(cons.lbg)
        self.ubg = np.concatenate(cons.ubg)
        self.n_g = cons.n
        # unpacking helpers
        sizes = [P] + [nx * (m * d + 1) for m in self.mesh] + [nu * m * d for m in self.mesh]
        sizes.append(nu * len(self.reset_events))  # V: the resets' controls, bounded as U
        self._offsets = np.concatenate([[0], np.cumsum(sizes)])
        self.lbx, self.ubx = self._variable_bounds()
        self._solvers: dict[bool, Any] = {}
        self.callback: _IterationCallback | None = None

    @staticmethod
    def _symbol_type(ocp: HybridOCP) -> Any:
        """SX symbols (a much faster NLP) unless a problem function is an MX graph (e.g. it
        calls an integrator), which cannot be evaluated on SX."""
        funcs = (
            [ocp.f, ocp.L, ocp.phi] + [g.psi for g in ocp.guards] + [g.reset for g in ocp.guards]
        )
        funcs += [fn for fn in (ocp.path, ocp.terminal_eq, ocp.terminal_ineq) if fn is not None]
        return ca.MX if any(fn.is_a("MXFunction") for fn in funcs) else ca.SX

    def _phys_x(self, X: Any) -> Any:
        """The physical states ``sigma_s X + s0`` of scaled state symbols ``(nx, n)``."""
        if not self.scaled:
            return X
        n = X.size2()
        return X * ca.repmat(ca.DM(self.sx), 1, n) + ca.repmat(ca.DM(self.off), 1, n)

    def _phys_u(self, U: Any) -> Any:
        """The physical controls ``sigma_u U`` of scaled control symbols ``(nu, n)``."""
        if not self.scaled:
            return U
        return U * ca.repmat(ca.DM(self.su), 1, U.size2())

    def _add_phase(self, cons: _Constraints, cost: Any, k: int, hk: Any, X: Any, U: Any) -> Any:
        """Phase ``k``'s collocation defects, control-polynomial bounds, path constraints and
        free-space guards; returns ``cost`` plus the phase's running cost (physical units;
        ``hk`` the physical duration, ``X``, ``U`` the scaled symbols)."""
        ocp, d, M = self.ocp, self.d, self.mesh[k]
        f, L, con = ocp.f, ocp.L, ocp.path
        u_lo, u_hi = np.asarray(ocp.u_min, dtype=float), np.asarray(ocp.u_max, dtype=float)
        bounded = np.flatnonzero(np.isfinite(u_lo) | np.isfinite(u_hi))
        su_b = self.su[bounded]
        if self.scaled:
            u_lo, u_hi = u_lo / self.su, u_hi / self.su
        lo_b, hi_b = np.tile(u_lo[bounded], d - 1), np.tile(u_hi[bounded], d - 1)
        D = ca.DM(self.rad.D)
        frac = self.fractions[k]
        Xp, Up = self._phys_x(X), self._phys_u(U)
        # a defect row of state i is divided by sigma_s,i (X D is already scaled: the
        # columns of D sum to zero, so the offset drops out exactly)
        sx_cols = ca.repmat(ca.DM(self.sx), 1, d)
        for e in range(M):
            he = hk / M if frac is None else hk * float(frac[e])
            Xe = X[:, e * d : e * d + d + 1]
            Ue = U[:, e * d : e * d + d]
            Xpe, Upe = Xp[:, e * d + 1 : e * d + d + 1], Up[:, e * d : e * d + d]
            Fe = f.map(d)(Xpe, Upe)
            if self.scaled:
                Fe = Fe / sx_cols
            cons.add(f"coll{k}", ca.mtimes(Xe, D) - he * Fe, 0.0, 0.0, np.tile(self.sx, d))
            Le = L.map(d)(Xpe, Upe)
            cost = cost + he * ca.mtimes(Le, ca.DM(self.rad.w))
            if bounded.size and d > 1:
                # the control polynomial stays within the bounds between the Radau points
                # too: its Bernstein coefficients do (the last one is the value at the
                # element end, a Radau point, bounded by lbx/ubx)
                bern = ca.mtimes(Ue[bounded.tolist(), :], ca.DM(self.rad.bernstein[:-1].T))
                cons.add(f"ubern{k}", bern, lo_b, hi_b, np.tile(su_b, d - 1))
            if con is not None:
                # path constraints at the Radau points (and the phase start, with the first
                # control of the phase)
                if e == 0:
                    cons.add(f"con{k}", con(Xp[:, 0], Up[:, 0]), 0.0, np.inf)
                cons.add(f"con{k}", con.map(d)(Xpe, Upe), 0.0, np.inf)
        # every guard stays in free space at the nodes, except the ones that are zero by
        # construction at this phase's boundaries (their equality constraint covers them)
        prev = self.guards[k - 1] if k > 0 else None
        nxt = self.guards[k] if k < self.P - 1 else None
        for gi, g in enumerate(ocp.guards):
            cols = list(range(M * d + 1))
            if gi == prev:
                cols = cols[1:]
            if gi == nxt:
                cols = cols[:-1]
            if cols:
                rows = g.psi.map(len(cols))(Xp[:, cols])
                if self.scaled:
                    rows = rows / self.gs[gi]
                cons.add(f"path{k}", rows, 0.0, np.inf, self.gs[gi])
        return cost

    def _add_event(self, cons: _Constraints, k: int, X: Any, U: Any, X_next: Any) -> None:
        """The ``k``-th event at the end of phase ``k``: its guard, the approach condition
        and the reset linking phase ``k + 1``."""
        ocp = self.ocp
        gs = float(self.gs[self.guards[k]])
        gd = ocp.guards[self.guards[k]]
        s_minus = self._phys_x(X[:, -1])
        u_minus = self._phys_u(U[:, -1])
        s_ = self.sym.sym("s", ocp.nx)
        dpsi = ca.Function("dpsi", [s_], [ca.jacobian(gd.psi(s_), s_)])
        approach = ca.mtimes(dpsi(s_minus), ocp.f(s_minus, u_minus))
        v = self.V_sym[:, self.reset_events.index(k)] if gd.uses_control else None
        if not self.scaled:
            cons.add(f"guard{k}", gd.psi(s_minus), 0.0, 0.0)
            cons.add(f"approach{k}", approach, -np.inf, 0.0)
            cons.add(f"link{k}", X_next[:, 0] - gd.reset_at(s_minus, v), 0.0, 0.0)
            return
        cons.add(f"guard{k}", gd.psi(s_minus) / gs, 0.0, 0.0, gs)
        cons.add(f"approach{k}", approach * (self.ts / gs), -np.inf, 0.0, gs / self.ts)
        # the jump as an increment, g(s) - s: the components it keeps (a collision's
        # positions) link exactly, without the rounding of s0 + sigma_s X - s0
        v = None if v is None else self._phys_u(v)
        jump = (gd.reset_at(s_minus, v) - s_minus) / ca.DM(self.sx)
        cons.add(f"link{k}", X_next[:, 0] - X[:, -1] - jump, 0.0, 0.0, self.sx)

    def _variable_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``lbx``, ``ubx``: phase durations in ``[1e-6 T, T]`` (``[1e-6 T_min, T_max]`` for
        a free final time), every Radau-point control in the control bounds, the states
        free."""
        ocp, P = self.ocp, self.P
        T_lo, T_hi = _horizon_range(ocp)
        lbx = np.full(self.n_w, -np.inf)
        ubx = np.full(self.n_w, np.inf)
        u_lo, u_hi = np.asarray(ocp.u_min, dtype=float), np.asarray(ocp.u_max, dtype=float)
        if self.scaled:
            T_lo, T_hi = T_lo / self.ts, T_hi / self.ts
            u_lo, u_hi = u_lo / self.su, u_hi / self.su
        lbx[:P] = 1e-6 * T_lo
        ubx[:P] = T_hi
        # U is stored column by column
        o = self._offsets
        n_u = int(o[-1] - o[1 + P])
        lbx[o[1 + P] :] = np.resize(u_lo, n_u)
        ubx[o[1 + P] :] = np.resize(u_hi, n_u)
        return lbx, ubx

    def solver(self, verbose: bool) -> Any:
        if verbose not in self._solvers:
            if self.callback is None:
                self.callback = _IterationCallback(self.n_w, self.n_g, self.lbg, self.ubg, self.cs)
            opts = {
                "ipopt.tol": 1e-12,
                "ipopt.acceptable_tol": max(1e-9, 100 * _rounding_level(self.ocp)),
                "ipopt.max_iter": _MAX_ITER,
                "ipopt.print_level": 5 if verbose else 0,
                "ipopt.sb": "yes",
                "print_time": bool(verbose),
                "iteration_callback": self.callback,
            }
            if self.ocp.has_terminal_constraints:
                # IPOPT relaxes constraint bounds by 1e-8 (relative) by default: an active
                # terminal inequality would then end violated by the judge's tolerance
                opts["ipopt.bound_relax_factor"] = 0.0
            self._solvers[verbose] = ca.nlpsol("dt", "ipopt", self._nlp, opts)
        return self._solvers[verbose]

    # --- packing ------------------------------------------------------------------------
    def pack(
        self,
        h: np.ndarray,
        X: list[np.ndarray],
        U: list[np.ndarray],
        V: np.ndarray | None = None,
    ) -> np.ndarray:
        """The NLP's (scaled) variables of physical durations ``h``, states ``X`` and
        controls ``U``; ``V`` ``(nu, len(reset_events))``: the resets' controls (default:
        the control at the end of each phase that ends in such an event)."""
        h = np.asarray(h, dtype=float)
        X = [np.asarray(x, dtype=float) for x in X]
        U = [np.asarray(u, dtype=float) for u in U]
        if self.reset_events and V is None:
            V = np.column_stack([U[k][:, -1] for k in self.reset_events])
        if self.scaled:
            h = h / self.ts
            X = [(x - self.off[:, None]) / self.sx[:, None] for x in X]
            U = [u / self.su[:, None] for u in U]
            if V is not None:
                V = np.asarray(V, dtype=float) / self.su[:, None]
        parts = [h]
        parts += [x.ravel(order="F") for x in X]
        parts += [u.ravel(order="F") for u in U]
        if self.reset_events:
            parts.append(np.asarray(V, dtype=float).ravel(order="F"))
        return np.concatenate(parts)

    def unpack_v(self, w: np.ndarray) -> np.ndarray:
        """The resets' physical controls ``(nu, len(reset_events))`` of the variables ``w``."""
        o, nu = self._offsets, self.ocp.nu
        V = w[o[-2] : o[-1]].reshape((nu, len(self.reset_events)), order="F").copy()
        return V * self.su[:, None] if self.scaled else V

    def unpack(self, w: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
        """The physical durations, states and controls of the (scaled) variables ``w``."""
        o, P, nx, nu, d = self._offsets, self.P, self.ocp.nx, self.ocp.nu, self.d
        h = w[:P].copy()
        X = [
            w[o[1 + k] : o[2 + k]].reshape((nx, self.mesh[k] * d + 1), order="F") for k in range(P)
        ]
        U = [
            w[o[1 + P + k] : o[2 + P + k]].reshape((nu, self.mesh[k] * d), order="F")
            for k in range(P)
        ]
        if self.scaled:
            h = h * self.ts
            X = [x * self.sx[:, None] + self.off[:, None] for x in X]
            U = [u * self.su[:, None] for u in U]
        return h, X, U

    def node_times(self, h: np.ndarray) -> list[np.ndarray]:
        """Times of the ``M d + 1`` state nodes of each phase."""
        starts = np.concatenate([[0.0], np.cumsum(h)[:-1]])
        out = []
        for k in range(self.P):
            M, frac = self.mesh[k], self.fractions[k]
            if frac is None:
                he = h[k] / M
                loc = (np.arange(M)[:, None] + self.rad.tau[None, 1:]).ravel()
                out.append(starts[k] + he * np.concatenate([[0.0], loc]))
            else:
                edges = self.edges(k)
                loc = (edges[:-1, None] + frac[:, None] * self.rad.tau[None, 1:]).ravel()
                out.append(starts[k] + h[k] * np.concatenate([[0.0], loc]))
        return out

    def shares(self, k: int) -> np.ndarray:
        """Phase ``k``'s element shares of its duration (summing to 1)."""
        frac = self.fractions[k]
        return np.full(self.mesh[k], 1.0 / self.mesh[k]) if frac is None else frac

    def edges(self, k: int) -> np.ndarray:
        """Phase ``k``'s element boundaries as fractions of its duration, ``0`` to ``1``."""
        frac = self.fractions[k]
        if frac is None:
            return np.arange(self.mesh[k] + 1) / self.mesh[k]
        edges = np.concatenate([[0.0], np.cumsum(frac)])
        edges[-1] = 1.0
        return edges

    def mult(self, lam_g: np.ndarray, name: str) -> list[np.ndarray]:
        """The multipliers of the constraints ``name`` in physical units: a row divided by
        ``r`` in an objective divided by ``sigma_J`` has ``sigma_J / r`` times them."""
        out = [lam_g[s] for s in self.g_index.get(name, [])]
        if not self.scaled:
            return out
        return [self.cs * m / r for m, r in zip(out, self.g_scale.get(name, []), strict=True)]

    def clip_controls(self, U: np.ndarray) -> np.ndarray:
        """Controls ``(nu, n)`` clipped into the problem's bounds."""
        lo = np.asarray(self.ocp.u_min, dtype=float)[:, None]
        hi = np.asarray(self.ocp.u_max, dtype=float)[:, None]
        return np.clip(U, lo, hi)


class _Stopped(HybridocError):
    """A :func:`solve_dt` run stopped by its time limit (what :func:`solve_dt` raises when no
    candidate was judged yet; otherwise it returns the best one as ``not-converged``)."""


class _Monitor:
    """Progress, the time limit and the candidates judged so far of one :func:`solve_dt`
    run (what a stopped or interrupted run returns)."""

    def __init__(self, progress: Progress, time_limit: float | None) -> None:
        self.progress = progress
        self.reporting = not isinstance(progress, NullProgress)
        self.time_limit = time_limit
        self.deadline = None if time_limit is None else time.perf_counter() + time_limit
        self.interrupted = False  # SIGINT arrived in IPOPT's iteration callback
        self.judged: list[_Judged] = []
        self.tried: list[dict[str, Any]] = []
        self.perturbation = 0.0

    def expired(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    def best(self) -> _Judged | None:
        """The best candidate judged so far: the cheapest feasible one that reproduces its
        events, else the cheapest that reproduces them, else the cheapest re-simulated."""
        ranked = [j for j in self.judged if j.ev is not None]
        if not ranked:
            return None

        def rank(j: _Judged) -> tuple[int, float]:
            assert j.ev is not None
            ok = _sequence_matches(j.result._nlp.ocp, j.result, j.ev)
            return (0 if ok and j.feasible else 1 if ok else 2, float(j.ev.cost))

        return min(ranked, key=rank)

    def stop(self, where: str) -> HybridocError:
        """The error of a run stopped by its time limit ``where``."""
        return _Stopped(
            f"dt: stopped at the time limit of {self.time_limit:g} s {where}; raise "
            "--time-limit, or make the NLP smaller and easier: a smaller --mesh, fewer events "
            "(--sequence, another --initial), fewer bodies, or --method gd"
        )


# the solve_dt run in progress: its IPOPT solves report to it, however deep they are called
_MONITOR: ContextVar[_Monitor | None] = ContextVar("hybridoc_dt_monitor", default=None)


class _IterationCallback(ca.Callback):
    """IPOPT's iteration callback: reports the iteration to the run's :class:`_Monitor` and
    asks IPOPT to stop (``User_Requested_Stop``) once its time limit has passed."""

    def __init__(
        self, n_w: int, n_g: int, lbg: np.ndarray, ubg: np.ndarray, cost_scale: float = 1.0
    ) -> None:
        ca.Callback.__init__(self)
        self.n_w, self.n_g, self.lbg, self.ubg = n_w, n_g, lbg, ubg
        self.cost_scale = cost_scale
        self.monitor: _Monitor | None = None
        self.iteration = 0
        self.construct("dt_iteration", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "stop"

    def get_sparsity_in(self, i: int) -> Any:
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.scalar()
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self.n_w)
        if name in ("g", "lam_g"):
            return ca.Sparsity.dense(self.n_g)
        return ca.Sparsity(0, 0)

    def eval(self, arg: list[Any]) -> list[int]:
        try:
            return self._eval(arg)
        except KeyboardInterrupt:
            # SIGINT during IPOPT surfaces here, the first Python code it runs: ask IPOPT
            # to stop, and let the run return what it has judged (solve_dt)
            if self.monitor is None:
                raise
            self.monitor.interrupted = True
            return [1]

    def _eval(self, arg: list[Any]) -> list[int]:
        self.iteration += 1
        mon = self.monitor
        if mon is None:
            return [0]
        if mon.reporting:
            g = np.asarray(arg[ca.nlpsol_out().index("g")], dtype=float).ravel()
            viol = float(np.max(np.maximum(self.lbg - g, g - self.ubg), initial=0.0))
            f = float(arg[ca.nlpsol_out().index("f")]) * self.cost_scale
            mon.progress.detail(
                f"IPOPT iteration {self.iteration} of at most {_MAX_ITER}, objective {f:.6g}, "
                f"constraint violation {viol:.1e}"
            )
        return [1 if mon.expired() else 0]


def _rounding_level(ocp: HybridOCP) -> float:
    """The relative rounding of the problem's functions at its states, in scaled units:
    ``eps max(1, max |s0_i| / sigma_i)`` (``s0`` the initial state). A problem far from the
    origin in its own lengths (positions ``3e5`` with lengths ``1e-3``) evaluates its guards
    and costs on positions rounded to ``eps |s|``, noise that no iterate can push below:
    IPOPT's acceptable level is set above it (``1e-9`` otherwise)."""
    x0 = np.abs(np.asarray(ocp.x0, dtype=float))
    return float(np.finfo(float).eps * max(1.0, float(np.max(x0 / ocp.scales.state_array))))


def _guard_scales(ocp: HybridOCP) -> np.ndarray:
    """Per guard, the scale its rows (guard, free space, approach) are divided by in the
    NLP: the power of two at or below the norm of ``d psi / d s~`` (the guard's gradient in
    the scaled state) at the initial state, so that a distance is measured in the
    problem's lengths (a disc pair's gap has the norm ``sqrt(2) L``, a wall's ``L``: both
    give ``L``). The problem's length scale where the gradient is zero or not finite; ones
    where the scales are the identity (the NLP of before)."""
    n = len(ocp.guards)
    sc = ocp.scales
    if sc.is_identity or not n:
        return np.ones(n)
    known = _GUARD_SCALES.get(ocp)
    if known is not None:  # once per problem, not per mesh of the refinement
        return known
    x0 = np.asarray(ocp.x0, dtype=float)
    s = ca.MX.sym("s", ocp.nx)
    out = np.full(n, float(sc.length))
    for i, g in enumerate(ocp.guards):
        grad = ca.Function("dpsi", [s], [ca.jacobian(g.psi(s), s)])
        norm = float(np.linalg.norm(np.asarray(grad(x0), dtype=float).ravel() * sc.state_array))
        if norm > 0 and math.isfinite(norm):
            # + 0.01: a unit normal's norm computed as 0.9999999999999999 still gives 1
            out[i] = math.ldexp(1.0, math.floor(math.log2(norm) + 0.01))
    _GUARD_SCALES[ocp] = out
    return out


def _horizon_range(ocp: HybridOCP) -> tuple[float, float]:
    """The final time's range: ``(T, T)``, or ``horizon_bounds`` when it is free."""
    if ocp.horizon_bounds is not None:
        return ocp.horizon_bounds
    return ocp.horizon, ocp.horizon


def _terminal_count(ocp: HybridOCP) -> int:
    """The number of terminal constraints (equalities and inequalities)."""
    fns = (ocp.terminal_eq, ocp.terminal_ineq)
    return sum(int(fn.size1_out(0)) for fn in fns if fn is not None)


def nlp_size(
    ocp: HybridOCP, guards: Sequence[int], degree: int, mesh: Sequence[int]
) -> tuple[int, int]:
    """``(variables, constraints)`` of the transcribed NLP of one sequence, without building
    it (the same count as :class:`_PhaseNLP`: states and controls at the nodes, collocation
    defects, every other guard at every node, links, bounds' Bernstein coefficients and
    path constraints).

    Parameters
    ----------
    ocp
        The problem.
    guards
        Guard indices of the events, in order.
    degree, mesh
        Collocation degree and elements per phase (one per phase).
    """
    nx, nu, d = ocp.nx, ocp.nu, degree
    P = len(guards) + 1
    n_b = int(np.count_nonzero(np.isfinite(ocp.u_min) | np.isfinite(ocp.u_max)))
    n_c = 0 if ocp.path is None else int(ocp.path.size1_out(0))
    n_w = P + sum(nx * (m * d + 1) + nu * m * d for m in mesh)
    n_w += nu * sum(ocp.guards[g].uses_control for g in guards)  # the resets' controls
    n_g = 1 + nx + _terminal_count(ocp)
    for k, m in enumerate(mesh):
        n_g += m * nx * d
        if n_b and d > 1:
            n_g += m * n_b * (d - 1)
        n_g += n_c * (m * d + 1)
        n_g += len(ocp.guards) * (m * d + 1)
        n_g -= (k > 0) + (k < P - 1)  # the phase's own boundary guards
        if k < P - 1:
            n_g += 2 + nx  # guard, approach, link
    return n_w, n_g


def _check_size(ocp: HybridOCP, guards: Sequence[int], degree: int, mesh: Sequence[int]) -> None:
    """A :class:`SceneError` naming the estimate when the NLP exceeds :data:`MAX_NLP_SIZE`."""
    n_w, n_g = nlp_size(ocp, guards, degree, mesh)
    if n_w + n_g > MAX_NLP_SIZE:
        m = sorted(set(mesh))
        raise SceneError(
            f"the transcription of this {len(guards)}-event sequence would have {n_w} variables "
            f"and {n_g} constraints ({len(guards) + 1} phases x {'/'.join(map(str, m))} elements x "
            f"degree {degree}, {ocp.nx} states, {len(ocp.guards)} guard(s) kept apart at every "
            f"node), more than MAX_NLP_SIZE = {MAX_NLP_SIZE} (IPOPT would run for hours); "
            "use a smaller --mesh, fewer events (--sequence, another --initial), fewer bodies, "
            "or --method gd"
        )


def _nlp_for(
    ocp: HybridOCP,
    guards: Sequence[int],
    degree: int,
    mesh: Sequence[int],
    fractions: Sequence[np.ndarray | None] | None = None,
) -> _PhaseNLP:
    cache = _NLPS.setdefault(ocp, {})
    shape = (
        None
        if fractions is None
        else tuple(None if f is None else tuple(float(x) for x in f) for f in fractions)
    )
    key = (tuple(guards), degree, tuple(mesh), shape)
    if key not in cache:
        _check_size(ocp, guards, degree, mesh)  # before minutes of building
        if len(cache) >= 64:  # the refinement's meshes: keep the newest
            cache.pop(next(iter(cache)))
        cache[key] = _PhaseNLP(ocp, guards, degree, mesh, fractions)
    return cache[key]


# ----------------------------------------------------------------------------------------
# initial guess from a simulated trajectory


def _match_events(ev: Evaluation, guards: Sequence[int], T: float) -> list[tuple[float, Any]]:
    """Event times (and the matched Event or None) for each guard of the sequence."""
    matched: list[tuple[float, Any]] = []
    start = 0
    for g in guards:
        hit = None
        for i in range(start, len(ev.events)):
            if ev.events[i].guard == g:
                hit = i
                break
        if hit is None:
            matched.append((np.nan, None))
        else:
            matched.append((ev.events[hit].time, ev.events[hit]))
            start = hit + 1
    # unmatched events: spread evenly between their matched neighbours
    times = np.array([m[0] for m in matched] + [T])
    prev_t = 0.0
    i = 0
    while i < len(matched):
        if np.isnan(times[i]):
            j = i
            while np.isnan(times[j]):
                j += 1
            nxt = times[j]
            for q in range(i, j):
                times[q] = prev_t + (nxt - prev_t) * (q - i + 1) / (j - i + 1)
                matched[q] = (times[q], None)
            i = j
        else:
            prev_t = times[i]
            i += 1
    # keep the phases ordered and non-degenerate
    out = []
    floor = 0.0
    K = len(matched)
    for q, (t, e) in enumerate(matched):
        t = min(max(t, floor + 1e-3 * T), T - 1e-3 * T * (K - q))
        out.append((t, e))
        floor = t
    return out


def _initial_point(
    nlp: _PhaseNLP, ev: Evaluation, controls: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ocp = nlp.ocp
    T = ocp.horizon
    matched = _match_events(ev, nlp.guards, T)
    bounds = np.array([0.0] + [m[0] for m in matched] + [T])
    h = np.diff(bounds)
    times = nlp.node_times(h)
    N = ocp.steps
    X, U = [], []
    for k in range(nlp.P):
        Xk = ev.sample(times[k]).T
        if k > 0 and matched[k - 1][1] is not None:
            Xk[:, 0] = matched[k - 1][1].state_after
        if k < nlp.P - 1 and matched[k][1] is not None:
            Xk[:, -1] = matched[k][1].state_before
        X.append(Xk)
        idx = np.clip((times[k][1:] / T * N).astype(int), 0, N - 1)
        U.append(nlp.clip_controls(np.asarray(controls, dtype=float)[idx].T))
    V = None
    if nlp.reset_events:
        # each reset's control: the guess's control in the cell of its event
        cells = [int(np.clip(bounds[k + 1] / T * N, 0, N - 1)) for k in nlp.reset_events]
        V = nlp.clip_controls(np.asarray(controls, dtype=float)[cells].T)
    return nlp.pack(h, X, U, V), h


# ----------------------------------------------------------------------------------------
# result


@dataclass
class DTResult:
    """The raw solution of the transcribed NLP for one sequence.

    Attributes
    ----------
    sequence
        Guard names of the events.
    nlp_cost
        The NLP objective.
    event_times
        ``gamma_1 .. gamma_K``.
    node_times, states
        Per phase: the state node times ``(M d + 1,)`` and states ``(nx, M d + 1)``.
    control_times, controls
        Per phase: Radau-point times and controls ``(nu, M d)``.
    costate_times, costates
        Costate estimates in time order (phase start from the link multiplier, then the
        Radau points); event times appear twice (after and before the jump).
    jump_multipliers
        Multipliers of the guard equations (``pi_k`` of the HMP jump condition, up to sign).
    lambda0
        ``lambda(0) = dJ/ds(0)``.
    horizon
        The final time, the sum of the phase durations (a decision variable for a free
        final time, clipped into its bounds).
    iterations, status
        IPOPT's counters.
    active_path
        Largest multiplier of the non-penetration constraints (non-zero: a guard outside the
        sequence is touched, a grazing contact).
    """

    sequence: list[str]
    nlp_cost: float
    event_times: np.ndarray
    node_times: list[np.ndarray]
    states: list[np.ndarray]
    control_times: list[np.ndarray]
    controls: list[np.ndarray]
    costate_times: np.ndarray
    costates: np.ndarray
    jump_multipliers: np.ndarray
    lambda0: np.ndarray
    horizon: float
    iterations: int
    status: str
    active_path: float
    element_bounds: np.ndarray
    _nlp: _PhaseNLP
    _w: np.ndarray

    event_controls: np.ndarray | None = None
    """``(K, nu)`` the control each event's reset reads (``v_k`` for a reset that depends on
    the control, the control at the phase's end for the others); ``None`` when no reset of
    the sequence depends on the control."""

    def control_function(self) -> Callable[[float], np.ndarray]:
        """The continuous-time control: per element, the polynomial through the Radau points
        (:meth:`control_at` at one time, bit for bit, for the judge's calls one at a time)."""
        nlp = self._nlp
        U_all = np.concatenate(self.controls, axis=1)
        vals = U_all.reshape(nlp.ocp.nu, -1, nlp.d)
        return _pieces_at_one_time(
            self.element_bounds, nlp.rad.tau[1:], vals, nlp.ocp.u_min, nlp.ocp.u_max
        )

    def control_at(self, t: np.ndarray) -> np.ndarray:
        """The control at the times ``t`` (vectorised), shape ``(len(t), nu)``."""
        nlp = self._nlp
        U_all = np.concatenate(self.controls, axis=1)  # (nu, total elements * d)
        vals = U_all.reshape(nlp.ocp.nu, -1, nlp.d)  # (nu, elements, d)
        # the Solution's own u(t) is this function of the arrays it saves, so the judged
        # cost of a saved dt Solution is this one bit for bit; the clip: the interpolating
        # polynomial may overshoot a bound between Radau points
        return lagrange_pieces(
            t, self.element_bounds, nlp.rad.tau[1:], vals, nlp.ocp.u_min, nlp.ocp.u_max
        )

    def cell_averages(self, grid: np.ndarray) -> np.ndarray:
        """Averages of the control over the cells of ``grid`` (exact for polynomial pieces)."""
        return _cell_averages(self.control_at, self.element_bounds, np.asarray(grid, dtype=float))


def solve_dt_sequence(
    ocp: HybridOCP,
    sequence: Sequence[str],
    *,
    guess: Evaluation,
    guess_controls: np.ndarray,
    degree: int = 3,
    mesh: int | Sequence[int] | None = None,
    verbose: bool = False,
) -> DTResult:
    """Solve the transcribed NLP for one event sequence.

    Parameters
    ----------
    ocp
        The problem.
    sequence
        Guard names of the events, in time order.
    guess, guess_controls
        A simulated trajectory and its ``(N, nu)`` controls, to initialise the phases.
    degree
        Collocation degree ``d`` (state polynomial degree), 1 to :data:`MAX_DEGREE`.
    mesh
        Elements per phase: one number for all phases or one per phase, 1 to
        :data:`MAX_MESH` each.
    verbose
        Print IPOPT's log.

    Returns
    -------
    DTResult

    Raises
    ------
    ConvergenceError
        IPOPT did not converge.
    """
    names = [g.name for g in ocp.guards]
    guards = [names.index(s) for s in ocp.check_sequence(sequence)]
    degree = _checked_degree(degree)
    P = len(guards) + 1
    mesh_list = _checked_mesh(mesh, P)
    nlp = _nlp_for(ocp, guards, degree, mesh_list)
    w0, _ = _initial_point(nlp, guess, guess_controls)
    return _solve_nlp(nlp, w0, list(sequence), verbose)


def _short_sequence(sequence: Sequence[str], most: int = 6) -> str:
    """A sequence for a message: the first few guards and how many more."""
    seq = list(sequence)
    if len(seq) <= most:
        return str(seq)
    return str(seq[:most])[:-1] + f", ... {len(seq) - most} more]"


def _is_int(x: Any) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool | np.bool_)


def _checked_degree(degree: Any) -> int:
    """``degree`` as an int in ``[1, MAX_DEGREE]``, or an :class:`OptionError`."""
    if not _is_int(degree) or not 1 <= degree <= MAX_DEGREE:
        raise OptionError(
            f"degree must be an integer from 1 to {MAX_DEGREE} (the Radau collocation tables "
            f"go up to {MAX_DEGREE}), got {degree!r}"
        )
    return int(degree)


def _checked_mesh(mesh: Any, phases: int | None) -> list[int]:
    """``mesh`` (None, one int or one per phase) as one int per phase; ``phases=None`` checks
    the values only (the number of phases depends on the candidate sequence)."""
    if mesh is None:
        mesh = _DEFAULT_MESH
    values = [mesh] if _is_int(mesh) else mesh
    if isinstance(values, str) or not isinstance(values, Sequence | np.ndarray):
        raise OptionError(f"mesh must be an integer or a list of integers, got {mesh!r}")
    values = list(values)
    if not values or not all(_is_int(m) and 1 <= m <= MAX_MESH for m in values):
        raise OptionError(
            f"mesh must be elements per phase, integers from 1 to {MAX_MESH}, got {mesh!r}"
        )
    if _is_int(mesh):
        return [int(mesh)] * (phases or 1)
    if phases is not None and len(values) != phases:
        raise OptionError(f"mesh must be one integer or {phases} (one per phase), got {mesh!r}")
    return [int(m) for m in values]


def _found_horizon(ocp: HybridOCP, h: np.ndarray) -> float:
    """The final time of the phase durations ``h``: ``T`` when fixed; for a free final time
    their sum, clipped into the bounds (IPOPT may relax a bound by about ``1e-8``)."""
    if ocp.horizon_bounds is None:
        return ocp.horizon
    lo, hi = ocp.horizon_bounds
    return float(min(max(float(np.sum(h)), lo), hi))


def _at(ocp: HybridOCP, r: DTResult) -> HybridOCP:
    """The problem at ``r``'s final time (itself for a fixed final time)."""
    if ocp.horizon_bounds is None or r.horizon == ocp.horizon:
        return ocp
    return ocp.replace(horizon=r.horizon)


def _solve_nlp(nlp: _PhaseNLP, w0: np.ndarray, sequence: list[str], verbose: bool) -> DTResult:
    """Run IPOPT on a transcribed NLP from ``w0`` and collect the result (reporting to the
    :func:`solve_dt` run in progress, if any)."""
    ocp, P = nlp.ocp, nlp.P
    monitor = _MONITOR.get()
    solver = nlp.solver(verbose)
    assert nlp.callback is not None
    nlp.callback.monitor, nlp.callback.iteration = monitor, 0
    try:
        res = solver(x0=w0, lbx=nlp.lbx, ubx=nlp.ubx, lbg=nlp.lbg, ubg=nlp.ubg)
    finally:
        nlp.callback.monitor = None
    stats = solver.stats()
    status = str(stats.get("return_status", ""))
    if monitor is not None and monitor.interrupted:
        # CasADi turns SIGINT inside IPOPT into NonIpopt_Exception_Thrown and swallows the
        # KeyboardInterrupt: the run's handler (solve_dt) set the flag
        raise KeyboardInterrupt
    if monitor is not None and status == "User_Requested_Stop" and monitor.expired():
        raise monitor.stop(
            f"in IPOPT iteration {nlp.callback.iteration} of the {P - 1}-event sequence "
            f"{_short_sequence(sequence)} ({nlp.n_w} variables, {nlp.n_g} constraints)"
        )
    if not stats.get("success", False) and status != "Solved_To_Acceptable_Level":
        g = np.asarray(res["g"]).ravel()
        viol = float(np.max(np.maximum(nlp.lbg - g, g - nlp.ubg), initial=0.0))
        what = "did not converge"
        hint = "try another initial guess or event sequence"
        if status in ("Infeasible_Problem_Detected", "Restoration_Failed"):
            # IPOPT's infeasibility is local: it stopped at a point that minimises the
            # constraint violation nearby, which proves nothing about the constraints
            what = (
                "stopped at a point of local infeasibility (IPOPT converged to a local "
                "minimum of the constraint violation: a local failure, not a proof that "
                "the constraints cannot be met)"
            )
            hint = (
                "start it elsewhere: another --initial guess (one whose simulation has these "
                "events, e.g. another method's solution), a finer --mesh, or another --sequence"
            )
        if _terminal_count(ocp) or ocp.horizon_bounds is not None:
            hint = (
                "the terminal constraints may be unreachable with these events, bounds and "
                "final time; " + hint
            )
        raise ConvergenceError(
            f"direct transcription for sequence {list(sequence)} {what} (IPOPT: {status}, "
            f"constraint violation {viol:.2e} after {int(stats.get('iter_count', -1))} "
            f"iterations); {hint}"
        )
    w = np.asarray(res["x"]).ravel()
    lam_g = np.asarray(res["lam_g"]).ravel()
    h, X, U = nlp.unpack(w)
    U = [nlp.clip_controls(Uk) for Uk in U]  # IPOPT may relax a bound by ~1e-8
    times = nlp.node_times(h)
    d, rad = nlp.d, nlp.rad

    # costates: phase start from the initial-condition / link multiplier, then Radau points
    ct: list[np.ndarray] = []
    cs: list[np.ndarray] = []
    lam0 = -nlp.mult(lam_g, "x0")[0]
    for k in range(P):
        start = lam0 if k == 0 else -nlp.mult(lam_g, f"link{k - 1}")[0]
        coll = nlp.mult(lam_g, f"coll{k}")
        lam_nodes = [
            -(c.reshape((ocp.nx, d), order="F") / rad.w[None, :]) for c in coll
        ]  # per element (nx, d)
        ct.append(times[k][:1])
        cs.append(start[None, :])
        ct.append(times[k][1:])
        cs.append(np.concatenate([ln.T for ln in lam_nodes], axis=0))
    jumps = np.array([nlp.mult(lam_g, f"guard{k}")[0][0] for k in range(P - 1)])
    path = [np.abs(m).max() for k in range(P) for m in nlp.mult(lam_g, f"path{k}") if m.size]
    bounds = [np.array([0.0])]
    for k in range(P):
        bounds.append(times[k][d::d])
    element_bounds = np.concatenate(bounds)
    event_controls = None
    if nlp.reset_events:
        V = nlp.clip_controls(nlp.unpack_v(w))
        event_controls = np.array([U[k][:, -1] for k in range(P - 1)], dtype=float)
        for i, k in enumerate(nlp.reset_events):
            event_controls[k] = V[:, i]
    return DTResult(
        sequence=list(sequence),
        nlp_cost=float(res["f"]) * nlp.cs if nlp.scaled else float(res["f"]),
        event_times=np.cumsum(h)[:-1],
        node_times=times,
        states=X,
        control_times=[t[1:] for t in times],
        controls=U,
        costate_times=np.concatenate(ct),
        costates=np.concatenate(cs, axis=0),
        jump_multipliers=jumps,
        lambda0=lam0,
        horizon=_found_horizon(ocp, h),
        iterations=int(stats.get("iter_count", -1)),
        status=status,
        active_path=float(max(path)) if path else 0.0,
        element_bounds=element_bounds,
        _nlp=nlp,
        _w=w,
        event_controls=event_controls,
    )


# ----------------------------------------------------------------------------------------
# sequence discovery and the public solver


def _sequence_of_events(ocp: HybridOCP, events: Sequence[Any]) -> list[str]:
    """Guard names of events given as :class:`Event` objects or ``{"bodies": ...}`` dicts."""
    out = []
    for e in events:
        if hasattr(e, "guard"):
            out.append(ocp.guards[e.guard].name)
            continue
        bodies = tuple(e["bodies"])
        hits = [g.name for g in ocp.guards if tuple(g.bodies) == bodies]
        if not hits:
            hits = [g.name for g in ocp.guards if g.name == "|".join(bodies)]
        if not hits:
            raise HybridocError(f"event with bodies {list(bodies)} matches no guard")
        out.append(hits[0])
    return out


def _initial_controls(ocp: HybridOCP, initial: Any) -> tuple[np.ndarray, list[str] | None]:
    """Controls (N, nu) and, when ``initial`` is a solution, its event sequence."""
    if initial is None:
        return np.asarray(ocp.u_guess, dtype=float), None
    controls = getattr(initial, "controls", None)
    if controls is not None and hasattr(initial, "events"):  # a Solution or an Evaluation
        u = ocp.check_controls(controls, what="initial controls")
        info = getattr(initial, "info", {}) or {}
        seq = info.get("sequence")
        if seq is None:
            seq = _sequence_of_events(ocp, initial.events)
        return u, list(seq)
    return ocp.check_controls(initial, what="initial controls"), None


def _candidates(observed: list[str]) -> list[list[str]]:
    """The observed sequence and every sequence with one of its events dropped."""
    out = [list(observed)]
    for i in range(len(observed)):
        cand = observed[:i] + observed[i + 1 :]
        if cand not in out:
            out.append(cand)
    return out


def _admissible_candidates(
    ocp: HybridOCP, cands: list[list[str]]
) -> tuple[list[list[str]], list[dict[str, Any]]]:
    """The candidates worth an NLP, and a record of those that are not: the observed
    sequence (the first) always, the others only where the modes admit them
    (:meth:`~hybridoc.HybridOCP.sequence_admissible`). On a problem with modes, dropping one
    event mostly leaves a sequence that fires a transition outside its source mode (the
    hopper's ``[touchdown, touchdown, liftoff]``): its NLP has no feasible point, and IPOPT
    took 30 to 40 iterations to say so (three of the hopper's five NLPs)."""
    if ocp.modes is None:
        return cands, []
    keep, skipped = cands[:1], []
    for cand in cands[1:]:
        if ocp.sequence_admissible(cand):
            keep.append(cand)
        else:
            skipped.append(
                {"sequence": cand, "nlp_cost": None,
                 "status": "not solved: the modes do not admit this sequence"}
            )  # fmt: skip
    return keep, skipped


def _resimulate(ocp: HybridOCP, r: DTResult) -> Evaluation:
    from hybridoc.callable_eval import evaluate_callable

    return evaluate_callable(
        _at(ocp, r),
        r.control_function(),
        breakpoints=r.element_bounds[1:-1],
        event_controls=r.event_controls,
    )


def _resimulated_names(ocp: HybridOCP, ev: Evaluation) -> list[str]:
    return [ocp.guards[e.guard].name for e in ev.events]


def _event_time_gap(ocp: HybridOCP, r: DTResult, ev: Evaluation) -> float | None:
    """Largest gap between modelled and re-simulated event times (``None``: other events)."""
    if _resimulated_names(ocp, ev) != r.sequence:
        return None
    times = np.array([e.time for e in ev.events])
    return float(np.max(np.abs(times - r.event_times), initial=0.0))


def _sequence_matches(ocp: HybridOCP, r: DTResult, ev: Evaluation, tol: float = 1e-6) -> bool:
    gap = _event_time_gap(ocp, r, ev)
    return gap is not None and gap <= tol * ocp.horizon


def _phase_durations(r: DTResult) -> list[float]:
    return [float(x) for x in np.diff(np.concatenate([[0.0], r.event_times, [r.horizon]]))]


def _lagrange_basis(pts: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Lagrange basis through ``pts`` evaluated at ``s``: shape ``(len(s), len(pts))``."""
    out = np.ones((s.size, pts.size))
    for j in range(pts.size):
        for m in range(pts.size):
            if m != j:
                out[:, j] *= (s - pts[m]) / (pts[j] - pts[m])
    return out


def _split_mesh(
    coarse: _PhaseNLP, split: Sequence[np.ndarray | None]
) -> tuple[list[int], list[np.ndarray | None]]:
    """The mesh with the elements ``split[k]`` (booleans per element of phase ``k``; ``None``:
    none) of each phase halved: its element counts and shares (``None`` where equal)."""
    mesh, fractions = [], []
    for k, which in enumerate(split):
        frac = coarse.fractions[k]
        if which is None or not np.any(which):
            mesh.append(coarse.mesh[k])
            fractions.append(frac)
            continue
        if frac is None and np.all(which):
            mesh.append(2 * coarse.mesh[k])  # uniform doubling: still equal elements
            fractions.append(None)
            continue
        shares = coarse.shares(k)
        new = np.concatenate(
            [[x / 2, x / 2] if w else [x] for x, w in zip(shares, which, strict=True)]
        )
        mesh.append(int(new.size))
        fractions.append(new)
    return mesh, fractions


def _refined(
    ocp: HybridOCP,
    r: DTResult,
    verbose: bool,
    phases: Sequence[int] | None = None,
    split: Sequence[np.ndarray | None] | None = None,
) -> DTResult:
    """Re-solve ``r``'s sequence on a finer mesh, started from ``r``'s state and control
    polynomials: the elements ``split`` (per phase, booleans per element) halved, or with
    ``split=None`` every element of the ``phases`` (default: every phase)."""
    coarse = r._nlp
    d, rad = coarse.d, coarse.rad
    if split is None:
        which = range(coarse.P) if phases is None else set(phases)
        split = [np.full(m, k in which) for k, m in enumerate(coarse.mesh)]
    fine_mesh, fine_fractions = _split_mesh(coarse, split)
    uniform = all(f is None for f in fine_fractions)
    fine = _nlp_for(ocp, coarse.guards, d, fine_mesh, None if uniform else fine_fractions)
    h, Xc, Uc = coarse.unpack(r._w)
    X, U = [], []
    for k in range(coarse.P):
        Mc, Mf = coarse.mesh[k], fine.mesh[k]
        if coarse.fractions[k] is None and fine.fractions[k] is None:
            loc = (np.arange(Mf)[:, None] + rad.tau[None, 1:]).ravel() / Mf  # in (0, 1]
            sigma = np.concatenate([[0.0], loc]) * Mc  # node positions in coarse elements
            e = np.clip(np.floor(sigma).astype(int), 0, Mc - 1)
            s = sigma - e
        else:
            fe, ce = fine.edges(k), coarse.edges(k)
            loc = (fe[:-1, None] + fine.shares(k)[:, None] * rad.tau[None, 1:]).ravel()
            pos = np.concatenate([[0.0], loc])  # node positions in the phase, 0 to 1
            e = np.clip(np.searchsorted(ce, pos, side="right") - 1, 0, Mc - 1)
            s = (pos - ce[e]) / coarse.shares(k)[e]
        bx = _lagrange_basis(rad.tau, s)  # (n, d + 1)
        cols = e[:, None] * d + np.arange(d + 1)[None, :]
        X.append(np.einsum("nr,xnr->xn", bx, Xc[k][:, cols]))
        su, eu = s[1:], e[1:]
        bu = _lagrange_basis(rad.tau[1:], su)  # (n, d)
        ucols = eu[:, None] * d + np.arange(d)[None, :]
        U.append(fine.clip_controls(np.einsum("nj,unj->un", bu, Uc[k][:, ucols])))
    V = coarse.unpack_v(r._w) if coarse.reset_events else None
    return _solve_nlp(fine, fine.pack(h, X, U, V), list(r.sequence), verbose)


_NUDGES = (1e-9, 1e-7)
"""Extensions (relative to ``T``) of each phase's last control piece past its event that
:func:`_nudged` tries, in order, on a candidate whose re-simulation misses its events."""


def _nudged(r: DTResult, delta: float) -> DTResult | None:
    """``r`` with each phase's last control polynomial extended ``delta`` past its event.

    The NLP puts each event exactly at a phase end: the guard is zero there and the next
    phase's control starts. Re-simulated, the control reaches the guard to within the
    integrator's and the collocation's errors; where the next phase's control stops the
    approach (a clock driven before a switch and frozen after it), a state that stopped
    ``1e-12`` short of the guard never crosses it. Extending the approaching phase's
    control polynomial over ``[gamma, gamma + delta]`` (one more element) and starting the
    next phase's at ``gamma + delta`` (its first element shrunk, the same polynomial in time)
    lets the trajectory cross the guard transversally, as the NLP's approach condition says
    it does. What this control does is judged like any other: it must reproduce the
    modelled events, and its cost is the judge's. ``None`` when ``delta`` is not below half
    of every phase's first element.
    """
    nlp = r._nlp
    if not r.sequence:
        return None
    rad, d, nu = nlp.rad, nlp.d, nlp.ocp.nu
    eb = np.asarray(r.element_bounds, dtype=float)
    vals = np.concatenate(r.controls, axis=1).reshape(nu, -1, d)
    nodes = rad.tau[1:]
    # the index of each phase's last element in the global element list
    ends = np.cumsum([c.shape[1] // d for c in r.controls])
    bounds, per_phase = [eb[0]], []
    for k in range(len(r.controls)):
        first = 0 if k == 0 else int(ends[k - 1])
        last = int(ends[k])
        phase_bounds, phase_vals = [], []
        for e in range(first, last):
            a, b, v = eb[e], eb[e + 1], vals[:, e, :]
            if k > 0 and e == first:
                # the extension of the previous phase's last piece, then this piece shrunk
                pa, pb, pv = eb[e - 1], eb[e], vals[:, e - 1, :]
                if not delta < 0.5 * (b - a):
                    return None
                t_ext = a + delta * nodes
                ext = pv @ _lagrange_basis(nodes, (t_ext - pa) / (pb - pa)).T
                phase_bounds.append(a + delta)
                phase_vals.append(ext)
                t_new = a + delta + (b - a - delta) * nodes
                v = v @ _lagrange_basis(nodes, (t_new - a) / (b - a)).T
            phase_bounds.append(b)
            phase_vals.append(v)
        bounds += phase_bounds
        per_phase.append(np.concatenate(phase_vals, axis=1))
    controls = [nlp.clip_controls(c) for c in per_phase]
    element_bounds = np.array(bounds)
    control_times = []
    i = 0
    for c in controls:
        n = c.shape[1] // d
        loc = element_bounds[i : i + n]
        he = element_bounds[i + 1 : i + n + 1] - loc
        control_times.append((loc[:, None] + he[:, None] * nodes[None, :]).ravel())
        i += n
    return dataclasses.replace(
        r, controls=controls, control_times=control_times, element_bounds=element_bounds
    )


def _nudge(ocp: HybridOCP, r: DTResult, terminal_tol: float) -> tuple[_Judged, float] | None:
    """The first of :data:`_NUDGES` whose :func:`_nudged` control reproduces ``r``'s events
    (judged), with the extension used; ``None`` if none does."""
    for rel in _NUDGES:
        rn = _nudged(r, rel * r.horizon)
        if rn is None:
            return None
        jn = _judge(ocp, rn, terminal_tol)
        if jn.ev is not None and _sequence_matches(ocp, rn, jn.ev):
            jn.nudge = rel * r.horizon
            return jn, jn.nudge
    return None


def _evaluate_guess(ocp: HybridOCP, u0: np.ndarray) -> tuple[Evaluation, np.ndarray, float]:
    """The judge's evaluation of the guess, its controls and the perturbation used.

    A guess whose events fire at the same instant without an order (a symmetric scene, a
    :class:`~hybridoc.errors.SimultaneousEventError`) is retried with the controls perturbed
    by ``1e-6 max(1, |u|) k z`` (``z`` one fixed-seed normal sample, ``k = 1, 2, 3``), so
    that the contacts happen one after the other and propose an event sequence.
    """
    try:
        return evaluate(ocp, u0), u0, 0.0
    except SimultaneousEventError as exc:
        first = exc
    z = np.random.default_rng(20240601).standard_normal(u0.shape)
    # in the controls' units: 1e-6 sigma_u max(1, |u / sigma_u|)
    su = ocp.scales.control_array
    scale = 1e-6 * max(1.0, float(np.abs(u0 / su).max(initial=0.0)))
    for k in range(1, _GUESS_PERTURBATIONS + 1):
        u = np.clip(u0 + scale * k * z * su, ocp.u_min, ocp.u_max)
        try:
            return evaluate(ocp, u), u, scale * k * float(np.max(su))  # in u's units
        except SimultaneousEventError:
            continue
    raise SimultaneousEventError(
        f"{first} (also with the initial guess perturbed by up to "
        f"{scale * _GUESS_PERTURBATIONS * float(np.max(su)):.1e}); give another initial guess "
        "or a sequence",
        guards=first.guards,
        time=first.time,
    ) from None


def _bound_tol(ocp: HybridOCP) -> float:
    """:data:`_BOUND_TOL` in the controls' units (the smallest control scale)."""
    return _BOUND_TOL * float(np.min(ocp.scales.control_array, initial=1.0))


@dataclass
class _Judged:
    """A converged candidate with its re-simulation by the judge."""

    result: DTResult
    ev: Evaluation | None
    error: str = ""
    terminal_tol: float = TERMINAL_TOL
    nudge: float = 0.0  # the extension of :func:`_nudged` that made it reproduce its events
    estimate: dict[str, Any] | None = None  # :func:`error_estimate`, where computed

    @property
    def feasible(self) -> bool:
        assert self.ev is not None
        return (
            self.ev.bound_violation <= _bound_tol(self.result._nlp.ocp)
            and self.ev.path_violation <= _PATH_TOL
            and self.ev.terminal_violation <= self.terminal_tol
        )


# ----------------------------------------------------------------------------------------
# the options


def _checked_time_limit(time_limit: Any) -> None:
    """An :class:`OptionError` unless ``time_limit`` is ``None`` or a positive finite number."""
    if time_limit is not None and not (
        isinstance(time_limit, int | float)
        and not isinstance(time_limit, bool)
        and math.isfinite(time_limit)
        and time_limit > 0
    ):
        raise OptionError(f"time_limit must be a positive number of seconds, got {time_limit!r}")


def _checked_terminal_tol(terminal_tol: Any) -> None:
    """An :class:`OptionError` unless ``terminal_tol`` is a positive finite number."""
    if not (isinstance(terminal_tol, int | float) and 0 < terminal_tol < math.inf):
        raise OptionError(f"terminal_tol must be a positive number, got {terminal_tol!r}")


def _parse_bounded_int(text: str, what: str, most: int) -> int:
    """Command-line text as an integer from 1 to ``most`` (a ``ValueError`` naming ``what``)."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= most:
        raise ValueError(f"{what} must be an integer from 1 to {most}, got {text!r}")
    return value


def _parse_mesh(text: str) -> int:
    return _parse_bounded_int(text, "mesh (collocation elements per phase)", MAX_MESH)


def _parse_degree(text: str) -> int:
    return _parse_bounded_int(text, "degree", MAX_DEGREE)


@dataclass(frozen=True)
class DTOptions:
    """The options of :func:`solve_dt` (``method="dt"``), declared once: their defaults are
    :func:`solve_dt`'s keywords' and ``hybridoc solve`` offers those with ``cli`` metadata as
    flags (``--sequence``, ``--mesh``, ``--degree``, ``--time-limit``, ``--terminal-tol``).

    Every value is checked when the options are made (:meth:`__post_init__`), the one place
    they are checked: an out-of-range ``degree``, ``mesh``, ``time_limit`` or
    ``terminal_tol`` is an :class:`~hybridoc.errors.OptionError`. What depends on the problem
    (``sequence``'s guard names, a ``mesh`` of one value per phase) is checked by
    :func:`run_dt` against the problem.
    """

    sequence: str | Sequence[str] | None = option(
        None,
        "comma-separated guard names in event order ('' for none)",
        metavar="EVENTS",
    )
    mesh: int | Sequence[int] | None = option(
        None,
        f"collocation elements per phase, at most {MAX_MESH} (default {_DEFAULT_MESH})",
        parse=_parse_mesh,
    )
    degree: int = option(
        3, f"collocation degree, 1 to {MAX_DEGREE} (default 3)", parse=_parse_degree
    )
    time_limit: float | None = option(
        None,
        "stop after this much wall time and exit 2, returning the best candidate judged so "
        f"far (default: no limit; at most {_MAX_ITER} IPOPT iterations per NLP)",
        parse=positive_float,
        metavar="SECONDS",
    )
    terminal_tol: float = option(
        TERMINAL_TOL,
        "the judged terminal-constraint violation above which a result is infeasible "
        f"(default {TERMINAL_TOL:g})",
        parse=positive_float,
        metavar="TOL",
    )
    verbose: bool = option(False, "print IPOPT's log and the candidates to stderr", cli=False)

    def __post_init__(self) -> None:
        """Check the options (:class:`~hybridoc.errors.OptionError`); ``degree`` becomes an
        ``int``."""
        object.__setattr__(self, "degree", _checked_degree(self.degree))
        _checked_mesh(self.mesh, None)
        _checked_time_limit(self.time_limit)
        _checked_terminal_tol(self.terminal_tol)


def _options_signature(run: Callable[..., Any], options: type) -> inspect.Signature:
    """``run``'s signature with its ``**options`` replaced by one keyword per field of the
    dataclass ``options``, with the field's default: what ``run`` accepts, and the defaults
    it applies, written once in the dataclass (:meth:`hybridoc.methods.Method.check_signature`
    and the documentation read it)."""
    sig = inspect.signature(run)
    params = [p for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD]
    params += [
        inspect.Parameter(
            f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default, annotation=f.type
        )
        for f in dataclasses.fields(options)
    ]
    return sig.replace(parameters=params)


# ----------------------------------------------------------------------------------------
# the public solver


def solve_dt(
    problem: ProblemLike,
    *,
    initial: ControlsLike | None = None,
    progress: ProgressLike = None,
    **options: Any,
) -> Solution:
    """Solve a hybrid OCP by multi-phase direct transcription (LGR collocation + IPOPT).

    The options are the fields of :class:`DTOptions`, with its defaults (where they are
    written, once); ``solve_dt(problem, **options)`` is
    ``run_dt(problem, DTOptions(**options))`` (:func:`run_dt`).

    Terminal constraints ``h(s(T)) = 0`` / ``>= 0`` are constraints of the NLP at the last
    phase's final node; a free final time (``horizon_bounds``) makes the sum of the phase
    durations a decision variable within its bounds.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP`, a :class:`~hybridoc.problems.Scene` or a built-in
        scene name.
    initial
        Initial guess: ``None`` (the problem's ``u_guess``), an ``(N, nu)`` control array, or
        a :class:`~hybridoc.solution.Solution` (its controls and its events). The phases are
        initialised from the guess's simulated trajectory. A guess whose simulation has two
        events at the same instant that do not commute (a symmetric scene) is perturbed by
        about ``1e-6`` so that they happen one after the other.
    progress
        ``True``: stage lines on stderr once the run has lasted a few seconds (a
        :class:`~hybridoc.progress.ProgressMeter`): the candidate, its NLP's size and
        IPOPT's iteration; ``False``/``None``: silent; or a caller's
        :class:`~hybridoc.progress.Progress`.
    sequence
        Event sequence as guard names, e.g. ``["ball1|ball2", "ball2|wall"]`` or the string
        ``"ball1|ball2,ball2|wall"`` (``[]``: no event). Default:
        discovered from ``initial``: its simulated events and every sequence with one of them
        dropped are solved, and the lowest-cost one whose control, re-simulated by the
        event-exact evaluator, produces exactly the modelled events is kept.
    degree
        Collocation degree, 1 to :data:`MAX_DEGREE` (``>= 3`` recommended; disc optima are
        cubic, so 3 is exact).
    mesh
        Collocation elements per phase (one int, or one per phase), 1 to :data:`MAX_MESH`
        each; default 4, refined: a candidate whose re-simulated events are the modelled
        ones at times off by a little (more than ``1e-6 T``, at most ``1e-3 T``) is solved
        once more with twice the elements, and a candidate that reproduces its events is
        refined until its error estimate is within the tolerances (:data:`REFINE_RTOL`,
        :data:`DEFECT_TOL`: the judged cost against the NLP objective and against the
        previous mesh, the collocation defects between the collocation points), the
        elements with too large defects halved, up to :data:`MAX_ADAPTIVE_MESH` elements
        per phase.
        A mesh given here is kept (its estimate is reported in ``info["error_estimate"]``;
        above the tolerances the result is ``not-converged``).
    time_limit
        Seconds of wall time: past them IPOPT (or the refinement) is stopped and the best
        candidate judged so far is returned as ``not-converged``; before any candidate is
        judged a :class:`~hybridoc.errors.HybridocError` names the limit (``None``: no
        limit; the work is at most one NLP of at most 500 IPOPT iterations per candidate,
        and the refinements). An interrupt (``KeyboardInterrupt``, SIGINT) returns the same
        way once a candidate has been judged.
    terminal_tol
        The judged terminal-constraint violation (of the re-simulated control) above which
        the result is :attr:`~hybridoc.solution.Status.INFEASIBLE`. The NLP meets the
        constraints at its collocated final state; the re-simulation misses them by the
        collocation's error, so at the default mesh a candidate above the tolerance is
        solved again with twice the elements, up to 4 times (mesh 64).
    verbose
        Print IPOPT's log and the candidates to stderr.

    Returns
    -------
    Solution
        Method ``"dt"``. ``cost`` and its parts are the continuous cost of the returned
        control ``u(t)`` re-simulated by :func:`hybridoc.evaluate_callable`; ``controls`` are
        cell averages of ``u(t)`` on the N-grid; ``costates`` are the multiplier estimates
        (events appear twice). ``info`` holds ``sequence``, ``event_times``, ``nlp_cost``,
        ``lambda0`` (``lambda(0)``, a warm start for the HMP reference), the candidates
        tried and IPOPT's counters, ``horizon`` (the final time: for a free final time the
        one found, at which :func:`hybridoc.evaluate` judges the solution and on which the
        grid of ``controls`` lies) and ``terminal_violation`` (the judge's). The callable
        control is available through :func:`control_function` on the solution.

        The NLP honours the control bounds at its Radau points (``u(t)`` is the Radau
        polynomial clipped into the bounds) and the path constraints at the Radau points and
        phase starts. When the re-simulation reproduces the modelled events and is
        feasible, ``status`` says what was compared (docs/solvers.rst, "dt: what its status
        claims"): :attr:`~hybridoc.solution.Status.EXTREMAL` for a given ``sequence`` (its
        optimum, not compared with other sequences);
        :attr:`~hybridoc.solution.Status.BEST_FOUND` for the default discovery on a problem
        with guards (the best of the guess's sequence and those with one event dropped,
        nothing more); :attr:`~hybridoc.solution.Status.SUCCESS` on a problem without
        guards (one sequence); :attr:`~hybridoc.solution.Status.NOT_OPTIMAL` instead of any
        of these when a cheaper feasible control is known (``info["cheaper"]``: the initial
        guess, an initial Solution's control, a candidate that re-simulated to other
        events); :attr:`~hybridoc.solution.Status.NOT_CONVERGED` when the default mesh's
        error estimate is still above the tolerances where the refinement stopped, or the
        time limit or an interrupt stopped the run (``info["stopped"]``). A candidate that
        misses its events by a hair is judged again with each phase's control extended
        ``1e-9 T`` (then ``1e-7 T``) past its event (``info["nudge"]``). Otherwise
        :attr:`~hybridoc.solution.Status.INFEASIBLE` when it reproduces them but violates
        the bounds (by more than ``1e-9``), the path constraints (by more than ``1e-6``) or
        the terminal constraints (by more than ``terminal_tol``) (a feasible candidate is
        preferred; ``message`` says by how much); :attr:`~hybridoc.solution.Status.EVENTS_DIFFER`
        when no converged candidate reproduces its events (the one with the lowest judged
        cost is returned; ``message`` names both sequences).

    Raises
    ------
    TypeError
        A keyword that is not an option of :class:`DTOptions`.
    OptionError
        ``degree``, ``mesh``, ``time_limit`` or ``terminal_tol`` is out of range, or a
        ``mesh`` per phase does not match the given ``sequence`` (a
        :class:`~hybridoc.errors.SceneError`).
    SceneError
        ``sequence`` names an event that is not a guard of the problem, or a candidate's
        NLP would have more than :data:`MAX_NLP_SIZE` variables and constraints
        (:func:`nlp_size`).
    HybridocError
        The run passed ``time_limit`` before any candidate was judged.
    ConvergenceError
        No candidate sequence's NLP converged (the message names IPOPT's status for each,
        e.g. ``Infeasible_Problem_Detected`` for terminal constraints it cannot meet).
    EvaluationError
        The judge cannot simulate the initial guess, or the control of any converged
        candidate (e.g. sustained contact).
    """
    unknown = [k for k in options if k not in _OPTION_NAMES]
    if unknown:
        raise TypeError(f"solve_dt() got an unexpected keyword argument {unknown[0]!r}")
    return run_dt(problem, DTOptions(**options), initial=initial, progress=progress)


solve_dt.__signature__ = _options_signature(solve_dt, DTOptions)  # type: ignore[attr-defined]
_OPTION_NAMES = frozenset(f.name for f in dataclasses.fields(DTOptions))


def run_dt(
    problem: ProblemLike,
    options: DTOptions | None = None,
    *,
    initial: ControlsLike | None = None,
    progress: ProgressLike = None,
) -> Solution:
    """:func:`solve_dt` with its options as one :class:`DTOptions` (checked when it was
    made; ``None``: the defaults).

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP`, a :class:`~hybridoc.problems.Scene` or a built-in
        scene name.
    options
        The options (:class:`DTOptions`).
    initial, progress
        As :func:`solve_dt`'s.

    Returns
    -------
    Solution
        As :func:`solve_dt`'s.
    """
    opts = DTOptions() if options is None else options
    ocp = as_ocp(problem)
    t_start = time.perf_counter()
    sequence = opts.sequence
    if sequence is not None:
        sequence = ocp.admissible_sequence(sequence)
        _checked_mesh(opts.mesh, len(sequence) + 1)  # one per phase of this sequence
    degree, mesh, verbose = opts.degree, opts.mesh, opts.verbose
    time_limit, terminal_tol = opts.time_limit, opts.terminal_tol
    with progress_scope(progress, "dt") as meter:
        monitor = _Monitor(meter, time_limit)
        token = _MONITOR.set(monitor)
        previous = flag_interrupts(monitor)
        try:
            return _solve_dt(
                ocp,
                sequence,
                initial,
                degree,
                mesh,
                verbose,
                monitor,
                t_start,
                float(terminal_tol),
            )
        except (_Stopped, KeyboardInterrupt) as exc:
            stopped = _stopped_solution(ocp, monitor, exc, degree, mesh, sequence, t_start)
            if stopped is None:
                raise
            return stopped
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)
            _MONITOR.reset(token)


def _stopped_solution(
    ocp: HybridOCP,
    monitor: _Monitor,
    exc: BaseException,
    degree: int,
    mesh: Any,
    sequence: list[str] | None,
    t_start: float,
) -> Solution | None:
    """The best candidate judged before the time limit or an interrupt (SIGINT), as a
    ``not-converged`` Solution whose message says why it stopped; ``None`` when nothing
    was judged yet (the error or the interrupt then goes on)."""
    best = monitor.best()
    if best is None:
        return None
    assert best.ev is not None
    why = (
        "interrupted (SIGINT)"
        if isinstance(exc, KeyboardInterrupt)
        else " ".join(str(exc).split()).removeprefix("dt: ")
    )
    ok = _sequence_matches(ocp, best.result, best.ev)
    if ok and best.feasible:
        what = "reproduces its events and is feasible"
    elif ok:
        what = "reproduces its events but violates a constraint"
    else:
        what = f"re-simulates to other events ({_resimulated_names(ocp, best.ev)})"
    message = (
        f"{why}: the best candidate judged so far is returned (sequence "
        f"{_short_sequence(best.result.sequence)}, mesh {list(best.result._nlp.mesh)}; it "
        f"{what}), without the comparison or refinement the run had left"
    )
    sol = _assemble(
        ocp,
        best,
        degree,
        mesh,
        sequence,
        monitor.tried,
        monitor.perturbation,
        time.perf_counter() - t_start,
    )
    sol.info["stopped"] = why
    return sol.set_status(Status.NOT_CONVERGED, message)


def _summary_lines(sol: Solution) -> list[tuple[str, str]]:
    """What ``hybridoc solve`` prints about a dt solution besides status, cost and events."""
    lines = []
    if "iterations" in sol.info:
        lines.append(("iterations", str(sol.info["iterations"])))
    if "nlp_cost" in sol.info:
        x = sol.info["nlp_cost"]
        text = "-" if x is None or math.isnan(float(x)) else f"{float(x):.12g}"
        lines.append(("nlp cost", f"{text} (the transcription's)"))
    if sol.info.get("free_horizon"):
        lines.append(("final time", f"{float(sol.info['horizon']):.12g} (free)"))
    if sol.info.get("terminal_constraints"):
        lines.append(
            (
                "constraints",
                f"terminal violated by {float(sol.info['terminal_violation']):.2e} (judged)",
            )
        )
        lines.append(("final mesh", " ".join(map(str, sol.info.get("mesh", [])))))
    return lines + settings_lines(sol)


METHOD = Method(
    "dt",
    "multi-phase direct transcription (Radau collocation, IPOPT)",
    run=solve_dt,
    options=DTOptions,
    tolerance=1e-6,
    summary_lines=_summary_lines,
    features=frozenset({"terminal", "free_horizon"}),
)
"""The ``"dt"`` method (:data:`hybridoc.methods.METHODS`): the transcription is exact for
polynomial optima, so crossval expects it within ``1e-6`` of the reference."""


def _solve_dt(
    ocp: HybridOCP,
    sequence: list[str] | None,
    initial: Any,
    degree: int,
    mesh: Any,
    verbose: bool,
    monitor: _Monitor,
    t_start: float,
    terminal_tol: float = TERMINAL_TOL,
) -> Solution:
    """:func:`solve_dt` after its arguments are checked: candidate sequences from the guess,
    their NLPs solved, the results judged, the best one assembled into a Solution."""
    monitor.progress.stage("simulating the initial guess")
    u0, seq_from_initial = _initial_controls(ocp, initial)
    guess, u0, perturbation = _evaluate_guess(ocp, u0)
    skipped: list[dict[str, Any]] = []
    if sequence is not None:
        cands = [list(sequence)]
    else:
        observed = seq_from_initial or [ocp.guards[e.guard].name for e in guess.events]
        cands, skipped = _admissible_candidates(ocp, _candidates(observed))
    monitor.perturbation = perturbation
    results, tried = _solve_candidates(ocp, cands, guess, u0, degree, mesh, verbose, monitor)
    tried += skipped
    matched, differ = _judge_candidates(
        ocp, results, tried, mesh, verbose, monitor.progress, terminal_tol
    )
    best_j, status, message = _choose(ocp, matched, differ, tried)
    status, message = _claim(ocp, best_j, status, message, sequence, cands, mesh)
    cheaper = _cheaper_known(ocp, best_j, guess, initial, differ)
    if cheaper is not None:
        what = (
            f"{cheaper['source']} costs {cheaper['cost']:.10g} (judged; events "
            f"{cheaper['sequence']}), less than this result's {best_j.ev.cost:.10g}"  # type: ignore[union-attr]
        )
        if status in (Status.SUCCESS, Status.EXTREMAL, Status.BEST_FOUND):
            status = Status.NOT_OPTIMAL
            message = (
                f"{what}: a cheaper control is known, so this is not the optimum; try "
                "--initial with that control, another --sequence, or --method reference"
            )
        else:
            message = f"{message}; {what}" if message else what
    solve_time = time.perf_counter() - t_start
    sol = _assemble(ocp, best_j, degree, mesh, sequence, tried, perturbation, solve_time)
    if best_j.estimate is not None:
        sol.info["error_estimate"] = _jsonable_estimate(best_j.estimate)
    sol.info["nudge"] = float(best_j.nudge)
    sol.info["cheaper"] = cheaper
    return sol.set_status(status, message)


def _claim(
    ocp: HybridOCP,
    j: _Judged,
    status: Status,
    message: str,
    sequence: list[str] | None,
    cands: list[list[str]],
    mesh: Any,
) -> tuple[Status, str]:
    """What a feasible candidate that reproduces its events may claim (docs/solvers.rst,
    "dt: what its status claims"): ``not-converged`` when its error estimate is above the
    tolerances (where the default mesh's refinement stopped, or at the user's mesh);
    ``extremal`` for a given
    sequence; ``best-found`` when the discovery did not compare every sequence the problem
    admits (any problem with a guard); ``success`` otherwise (no guard: the only sequence
    is the empty one). Other statuses pass unchanged."""
    if status is not Status.SUCCESS:
        return status, message
    est = j.estimate
    if est is not None and not est["converged"]:
        text = _estimate_text(est)
        if mesh is None:
            return Status.NOT_CONVERGED, (
                f"the error estimate is above the tolerance: {text}; the refinement stopped "
                f"at {est.get('stopped', 'its bound')} (try --degree 5 or a --time-limit; "
                "the judged cost is that of the returned control)"
            )
        # the user's mesh is kept, and what it claims is only what its estimate supports
        return Status.NOT_CONVERGED, (
            f"at the given mesh the error estimate is above the tolerance: {text}; without "
            "--mesh dt refines the mesh until it is met (the judged cost is that of the "
            "returned control)"
        )
    if sequence is not None:
        status, message = (
            Status.EXTREMAL,
            (
                f"the transcription's optimum for the given sequence {_short_sequence(sequence)}, "
                "not compared with other sequences (without --sequence dt compares its initial "
                "guess's sequences; --method reference searches for the optimum)"
            ),
        )
    elif ocp.guards:
        shown = ", ".join(_short_sequence(c) for c in cands[:4])
        more = f" and {len(cands) - 4} more" if len(cands) > 4 else ""
        status, message = (
            Status.BEST_FOUND,
            (
                f"the best of the {len(cands)} event sequence(s) compared ({shown}{more}: the "
                "initial guess's and those with one of its events dropped); other sequences were "
                "not compared, so a cheaper control may exist (--method reference searches for "
                "the optimum; --initial or --sequence start dt elsewhere)"
            ),
        )
    return status, message


def _cheaper_known(
    ocp: HybridOCP, j: _Judged, guess: Evaluation, initial: Any, differ: list[_Judged]
) -> dict[str, Any] | None:
    """The cheapest feasible control dt knows that costs less than ``j``'s (judged, by more
    than ``1e-9`` relative), or ``None``: the initial guess (as simulated), an initial
    Solution's own control, and the controls of candidates whose re-simulation gave other
    events. Feasible: within the bounds, the path and the terminal constraints (and the
    required final mode) by dt's tolerances; a cheaper control that violates them is no
    rival."""
    assert j.ev is not None

    def feasible(ev: Evaluation) -> bool:
        return _Judged(j.result, ev, terminal_tol=j.terminal_tol).feasible

    known: list[dict[str, Any]] = []
    is_solution = isinstance(initial, Solution)
    if feasible(guess):
        known.append(
            {
                "source": "the initial solution's controls on the grid"
                if is_solution
                else "the initial guess",
                "cost": float(guess.cost),
                "sequence": _resimulated_names(ocp, guess),
            }
        )
    if is_solution:
        try:
            own = evaluate(ocp, initial)
        except HybridocError:
            own = None
        if own is not None and feasible(own):
            known.append(
                {
                    "source": f"the initial solution ({initial.method})",
                    "cost": float(own.cost),
                    "sequence": _resimulated_names(ocp, own),
                }
            )
    for d in differ:
        if d.ev is not None and d.feasible:
            known.append(
                {
                    "source": f"the transcription's control for "
                    f"{_short_sequence(d.result.sequence)} (re-simulated to other events)",
                    "cost": float(d.ev.cost),
                    "sequence": _resimulated_names(ocp, d.ev),
                }
            )
    bound = float(j.ev.cost) * (1 - _CHEAPER_RTOL) - 1e-15 * ocp.scales.cost
    cheaper = [k for k in known if k["cost"] < bound]
    return min(cheaper, key=lambda k: k["cost"]) if cheaper else None


def _solve_candidates(
    ocp: HybridOCP,
    cands: list[list[str]],
    guess: Evaluation,
    u0: np.ndarray,
    degree: int,
    mesh: Any,
    verbose: bool,
    monitor: _Monitor,
) -> tuple[list[DTResult], list[dict[str, Any]]]:
    """The NLP of each candidate sequence solved from the guess: the converged results, and
    a record of every candidate tried."""
    results: list[DTResult] = []
    tried: list[dict[str, Any]] = monitor.tried
    names = [g.name for g in ocp.guards]
    for i, cand in enumerate(cands):
        if monitor.expired():
            raise monitor.stop(f"before candidate {i + 1} of {len(cands)}")
        guards = [names.index(c) for c in cand]
        mesh_list = _checked_mesh(mesh, len(cand) + 1)
        n_w, n_g = nlp_size(ocp, guards, degree, mesh_list)
        monitor.progress.stage(
            f"candidate {i + 1} of {len(cands)}: a {len(cand)}-event sequence, NLP of {n_w} "
            f"variables and {n_g} constraints"
        )
        try:
            nlp = _nlp_for(ocp, guards, degree, mesh_list)
            w0, _ = _initial_point(nlp, guess, u0)
            r = _solve_nlp(nlp, w0, list(cand), verbose)
        except ConvergenceError as exc:
            tried.append({"sequence": cand, "nlp_cost": None, "status": str(exc)})
            continue
        results.append(r)
        tried.append({"sequence": cand, "nlp_cost": r.nlp_cost, "status": r.status})
    if not results:
        why = "; ".join(f"{t['sequence']}: {t['status']}" for t in tried)
        raise ConvergenceError(
            "direct transcription did not converge for any event sequence (tried "
            f"{[t['sequence'] for t in tried]}); give an explicit sequence or another "
            f"initial guess. Per sequence: {why}"
        )
    return results, tried


def _judge(ocp: HybridOCP, r: DTResult, terminal_tol: float = TERMINAL_TOL) -> _Judged:
    """``r`` with the judge's re-simulation of its control (or the reason it failed); the
    run in progress keeps it (what a stopped run returns)."""
    try:
        j = _Judged(r, _resimulate(ocp, r), terminal_tol=terminal_tol)
    except EvaluationError as exc:
        j = _Judged(r, None, str(exc), terminal_tol=terminal_tol)
    monitor = _MONITOR.get()
    if monitor is not None:
        monitor.judged.append(j)
    return j


def _refine_terminal(
    ocp: HybridOCP, j: _Judged, verbose: bool, progress: Progress
) -> tuple[_Judged, bool]:
    """At the default mesh, a candidate that reproduces its events but whose re-simulated
    final state misses the terminal constraints by more than the tolerance (the
    collocation's error, which the NLP does not see) is solved again with twice the
    elements, up to :data:`_TERMINAL_REFINEMENTS` times: Radau collocation's error at the
    element ends falls as ``h^(2d-1)``. Returns the last judged candidate that still
    reproduces its events and whether it was refined."""
    refined = False
    for _ in range(_TERMINAL_REFINEMENTS):
        assert j.ev is not None
        if j.ev.terminal_violation <= j.terminal_tol:
            break
        progress.stage(
            f"refining the {len(j.result.sequence)}-event candidate (twice the mesh): the "
            f"judged terminal violation is {j.ev.terminal_violation:.1e}"
        )
        try:
            rf = _refined(ocp, j.result, verbose)
        except (ConvergenceError, SceneError):  # SceneError: beyond MAX_NLP_SIZE
            break
        jf = _judge(ocp, rf, j.terminal_tol)
        if jf.ev is None or not _sequence_matches(ocp, rf, jf.ev):
            break
        j, refined = jf, True
    return j, refined


def _judge_or_refine(
    ocp: HybridOCP,
    r: DTResult,
    mesh: Any,
    verbose: bool,
    progress: Progress,
    terminal_tol: float = TERMINAL_TOL,
) -> tuple[_Judged, bool, bool]:
    """The judged candidate, whether it reproduces its events, and whether it was refined:
    at the default mesh, a near miss (the same events at times off by a little) is solved
    again with twice the elements, since a finer mesh may fix it, up to
    :data:`_NEAR_MISS_REFINEMENTS` times while the event-time gap shrinks (a stance phase
    of the hopper, an oscillation, needs mesh 16), and so is a candidate that misses its
    terminal constraints (:func:`_refine_terminal`)."""
    j = _judge(ocp, r, terminal_tol)
    ok = j.ev is not None and _sequence_matches(ocp, r, j.ev)
    if not ok and j.ev is not None:
        # missed by a hair where the next phase's control stops the approach: judged again
        # with the approaching control extended past the event
        nudged = _nudge(ocp, r, terminal_tol)
        if nudged is not None:
            j, ok = nudged[0], True
    if ok and mesh is None:
        refined = False
        if ocp.has_terminal_constraints:
            j, refined = _refine_terminal(ocp, j, verbose, progress)
        j, adapted = _adapt(ocp, j, verbose, progress)
        return j, ok, refined or adapted
    if ok:  # the user's mesh: its error estimate is reported, not acted on
        j.estimate = _error_estimate(ocp, j)
        return j, ok, False
    if mesh is not None or j.ev is None:
        return j, ok, False
    gap = _event_time_gap(ocp, r, j.ev)
    if gap is None or not gap <= _NEAR_MISS * ocp.horizon:
        return j, ok, False
    best: _Judged | None = None
    for _ in range(_NEAR_MISS_REFINEMENTS):
        progress.stage(f"refining the {len(r.sequence)}-event candidate (twice the mesh)")
        try:
            rf = _refined(ocp, r if best is None else best.result, verbose)
        except (ConvergenceError, SceneError):  # SceneError: beyond MAX_NLP_SIZE
            break
        jf = _judge(ocp, rf, terminal_tol)
        if jf.ev is None:
            break
        gap_f = _event_time_gap(ocp, jf.result, jf.ev)
        if best is not None and (gap_f is None or not gap_f < gap):
            break  # no progress: the previous refinement stands
        best = jf
        if gap_f is None or _sequence_matches(ocp, jf.result, jf.ev):
            break
        gap = gap_f
    if best is None:
        return j, ok, False
    ok_f = _sequence_matches(ocp, best.result, best.ev)
    if ok_f and ocp.has_terminal_constraints:
        best = _refine_terminal(ocp, best, verbose, progress)[0]
    if ok_f:
        best = _adapt(ocp, best, verbose, progress)[0]
    return best, ok_f, True


def _defects(ocp: HybridOCP, r: DTResult) -> list[np.ndarray]:
    """Per phase and element, the largest collocation defect between the collocation points:
    ``h_e |x'(t_m) - f(x(t_m), u(t_m))|`` at the midpoints ``t_m`` of consecutive nodes of
    every element (``x`` the state polynomial, ``u`` the control polynomial clipped into the
    bounds), each state relative to ``max(1, max |x_i|)`` on the phase. The NLP makes the
    defect zero at the collocation points only; between them it is the local error of one
    element, which shrinks as ``h^(d+1)`` where the solution is smooth."""
    nlp = r._nlp
    d, rad = nlp.d, nlp.rad
    mids = 0.5 * (rad.tau[:-1] + rad.tau[1:])
    bx = _lagrange_basis(rad.tau, mids)  # (d, d + 1)
    dbx = np.zeros_like(bx)
    for j in range(d + 1):
        others = np.delete(rad.tau, j)
        poly = np.poly1d(others, r=True) / np.prod(rad.tau[j] - others)
        dbx[:, j] = np.polyder(poly)(mids)
    bu = _lagrange_basis(rad.tau[1:], mids)  # (d, d)
    lo = np.asarray(ocp.u_min, dtype=float)[:, None]
    hi = np.asarray(ocp.u_max, dtype=float)[:, None]
    h = np.diff(np.concatenate([[0.0], r.event_times, [r.horizon]]))
    f = ocp.f.map(d)
    sx, off = ocp.scales.state_array, ocp.scales.offset_array
    out = []
    for k in range(nlp.P):
        M = nlp.mesh[k]
        shares = nlp.shares(k)
        X, U = r.states[k], r.controls[k]
        # max(1, max |x_i|) in the state's units: sigma_i max(1, max |(x_i - s0_i) / sigma_i|)
        if ocp.scales.is_identity:
            scale = np.maximum(1.0, np.max(np.abs(X), axis=1))
        else:
            scale = sx * np.maximum(1.0, np.max(np.abs(X - off[:, None]) / sx[:, None], axis=1))
        per = np.zeros(M)
        for e in range(M):
            he = h[k] * float(shares[e])
            Xe, Ue = X[:, e * d : e * d + d + 1], U[:, e * d : e * d + d]
            xm = Xe @ bx.T
            fm = np.asarray(f(xm, np.clip(Ue @ bu.T, lo, hi)), dtype=float)
            dev = np.abs(Xe @ dbx.T - he * fm) / scale[:, None]
            per[e] = float(np.max(dev, initial=0.0))
        out.append(per)
    return out


def _error_estimate(
    ocp: HybridOCP, j: _Judged, previous_cost: float | None = None
) -> dict[str, Any]:
    """The error estimate of a judged candidate that reproduces its events: what the default
    mesh's refinement acts on (:data:`REFINE_RTOL`, :data:`DEFECT_TOL`).

    Returns
    -------
    dict
        ``cost_gap``: ``|judged cost - NLP objective| / max(1, |J|)``; ``refinement_change``:
        the same of the judged costs of this mesh and the previous one (``None`` before a
        refinement); ``defects``: :func:`_defects` per phase; ``event_time_gap``: the
        largest gap between modelled and re-simulated event times; ``phases``: the phases
        whose defect is above :data:`DEFECT_TOL` (where to refine); ``converged``: the cost
        gap within :data:`REFINE_RTOL` and, on the first mesh, the defects within
        :data:`DEFECT_TOL`, after a refinement the change within :data:`REFINE_RTOL`.
    """
    r, ev = j.result, j.ev
    assert ev is not None
    scale = max(ocp.scales.cost, abs(float(ev.cost)))  # max(1, |J|) in the cost's units
    gap = abs(float(ev.cost) - r.nlp_cost) / scale
    change = None if previous_cost is None else abs(float(ev.cost) - previous_cost) / scale
    per_element = _defects(ocp, r)
    defects = [float(np.max(x, initial=0.0)) for x in per_element]
    phases = [k for k, x in enumerate(defects) if not x <= DEFECT_TOL]
    time_gap = _event_time_gap(ocp, r, ev)
    # REFINE_RTOL, or above the rounding of a problem far from its origin (whose judged
    # cost carries that rounding, which no mesh removes)
    rtol = max(REFINE_RTOL, 100 * _rounding_level(ocp))
    if change is None:  # the first mesh: its defects must be small too
        converged = gap <= rtol and not phases
    else:  # refined: the last two meshes agree (the defects only say where to refine)
        converged = gap <= rtol and change <= rtol
    return {
        "tolerance": rtol,
        "cost_gap": gap,
        "refinement_change": change,
        "defects": defects,
        "event_time_gap": time_gap,
        "phases": phases,
        "converged": bool(converged),
        "mesh": list(r._nlp.mesh),
        "_split": [~(x <= DEFECT_TOL) for x in per_element],
    }


def _estimate_text(est: dict[str, Any]) -> str:
    """The error estimate for a message."""
    rtol = est.get("tolerance", REFINE_RTOL)
    parts = [f"judged cost vs NLP objective {est['cost_gap']:.2e} (relative)"]
    if est.get("refinement_change") is not None:
        parts.append(f"change from the previous mesh {est['refinement_change']:.2e}")
    parts.append(f"largest collocation defect {max(est['defects'], default=0.0):.2e}")
    return (
        ", ".join(parts) + f" at mesh {est['mesh']} (tolerances {rtol:g}, {rtol:g}, {DEFECT_TOL:g})"
    )


def _adapt(ocp: HybridOCP, j: _Judged, verbose: bool, progress: Progress) -> tuple[_Judged, bool]:
    """Refine the mesh of a candidate that reproduces its events until its error estimate
    (:func:`_error_estimate`) is within the tolerances, as h-adaptive direct methods do:
    the elements whose collocation defects are too large are halved (every element when
    only the costs disagree), the refined NLP is solved from the coarse solution and
    judged, and the estimate compares it with the previous mesh too. Stops at
    :data:`MAX_ADAPTIVE_MESH` elements per phase, after :data:`_MAX_ADAPTIONS` refinements,
    at :data:`MAX_NLP_SIZE`, or when a refined NLP fails or its control no longer
    reproduces the events; ``j.estimate`` then says what was not met (``stopped``).
    Returns the last candidate and whether it was refined."""
    refined = False
    previous: float | None = None
    previous_gap: float | None = None
    stalled = 0  # consecutive refinements that left the settled cost's gap as it was
    for _ in range(_MAX_ADAPTIONS):
        est = _error_estimate(ocp, j, previous)
        j.estimate = est
        if est["converged"]:
            return j, refined
        change = est["refinement_change"]
        settled = change is not None and change <= est["tolerance"]
        if settled and previous_gap is not None and est["cost_gap"] >= 0.9 * previous_gap:
            stalled += 1
        else:
            stalled = 0
        if stalled >= 2:
            # the judged cost has settled across meshes while the NLP's objective stays as
            # far from it, twice: finer meshes do not close that gap (at a grazing contact
            # the refinement went on for 12 rounds, 115 s, to the same numbers)
            est["stopped"] = (
                "the judged cost settled across meshes while the NLP objective stays "
                f"{est['cost_gap']:.2e} from it (two refinements did not close it)"
            )
            return j, refined
        previous_gap = est["cost_gap"]
        nlp = j.result._nlp
        if est["phases"]:
            split = [x if k in est["phases"] else None for k, x in enumerate(est["_split"])]
        else:  # only the costs disagree: every element
            split = [np.ones(m, dtype=bool) for m in nlp.mesh]
        counts, _ = _split_mesh(nlp, split)
        split = [None if n > MAX_ADAPTIVE_MESH else x for n, x in zip(counts, split, strict=True)]
        phases = [k for k, x in enumerate(split) if x is not None and np.any(x)]
        if not phases:
            est["stopped"] = f"the mesh bound MAX_ADAPTIVE_MESH = {MAX_ADAPTIVE_MESH} per phase"
            return j, refined
        monitor = _MONITOR.get()
        if monitor is not None and monitor.expired():
            raise monitor.stop(f"while refining the mesh ({_estimate_text(est)})")
        progress.stage(
            f"refining phase(s) {phases} of the {len(j.result.sequence)}-event candidate: "
            + _estimate_text(est)
        )
        try:
            rf = _refined(ocp, j.result, verbose, split=split)
        except SceneError:
            est["stopped"] = f"the NLP size bound MAX_NLP_SIZE = {MAX_NLP_SIZE}"
            return j, refined
        except ConvergenceError as exc:
            est["stopped"] = f"IPOPT failed on the refined mesh ({exc})"
            return j, refined
        jf = _judge(ocp, rf, j.terminal_tol)
        if jf.ev is None or not _sequence_matches(ocp, rf, jf.ev):
            nudged = None if jf.ev is None else _nudge(ocp, rf, j.terminal_tol)
            if nudged is None:
                est["stopped"] = "the refined mesh's control does not reproduce the events"
                return j, refined
            jf = nudged[0]
            jf.nudge = nudged[1]
        assert j.ev is not None
        previous = float(j.ev.cost)
        j, refined = jf, True
    # the last refinement's candidate, judged by the same estimate
    est = _error_estimate(ocp, j, previous)
    j.estimate = est
    if not est["converged"]:
        est["stopped"] = f"the most refinements, {_MAX_ADAPTIONS}"
    return j, refined


def _jsonable_estimate(est: dict[str, Any]) -> dict[str, Any]:
    """An error estimate with plain floats and lists, for ``info``."""
    out = {k: v for k, v in est.items() if not k.startswith("_")}
    out["defects"] = [float(x) for x in est["defects"]]
    for key in ("cost_gap", "refinement_change", "event_time_gap"):
        if out.get(key) is not None:
            out[key] = float(out[key])
    return out


def _record(
    ocp: HybridOCP, tried: list[dict[str, Any]], j: _Judged, ok: bool, refined: bool
) -> None:
    """Add the judge's verdict on ``j`` to its entry in ``tried``."""
    for t in tried:
        if t["sequence"] == j.result.sequence:
            t["resimulated"] = ok
            t["refined"] = refined
            if refined:
                t["nlp_cost"] = j.result.nlp_cost
                t["status"] = j.result.status
            if j.ev is None:
                t["resimulation_error"] = j.error
            else:
                t["resimulated_sequence"] = _resimulated_names(ocp, j.ev)
                t["judged_cost"] = float(j.ev.cost)
                t["terminal_violation"] = float(j.ev.terminal_violation)
                t["mesh"] = list(j.result._nlp.mesh)
            if j.nudge:
                t["nudge"] = j.nudge
            if j.estimate is not None:
                t["error_estimate"] = _jsonable_estimate(j.estimate)


def _judge_candidates(
    ocp: HybridOCP,
    results: list[DTResult],
    tried: list[dict[str, Any]],
    mesh: Any,
    verbose: bool,
    progress: Progress,
    terminal_tol: float = TERMINAL_TOL,
) -> tuple[list[_Judged], list[_Judged]]:
    """Re-simulate the converged candidates, in order of NLP cost, until one reproduces its
    events and is feasible. Returns those that reproduce their events and those that
    re-simulate to other events (or not at all)."""
    matched: list[_Judged] = []
    differ: list[_Judged] = []
    for r in sorted(results, key=lambda r: r.nlp_cost):
        progress.stage(f"re-simulating the {len(r.sequence)}-event candidate with the judge")
        j, ok, refined = _judge_or_refine(ocp, r, mesh, verbose, progress, terminal_tol)
        _record(ocp, tried, j, ok, refined)
        if verbose:
            print(
                f"dt: {j.result.sequence} cost {j.result.nlp_cost:.12g} valid {ok}"
                + (" (refined mesh)" if refined else ""),
                file=sys.stderr,
            )
        if ok:
            matched.append(j)
            if j.feasible:
                break
        else:
            differ.append(j)
    return matched, differ


def _choose(
    ocp: HybridOCP, matched: list[_Judged], differ: list[_Judged], tried: list[dict[str, Any]]
) -> tuple[_Judged, Status, str]:
    """The candidate to return, its status and message: the first feasible one that
    reproduces its events, else the first that reproduces them, else the one of lowest
    judged cost."""
    feasible = [j for j in matched if j.feasible]
    if feasible:
        return feasible[0], Status.SUCCESS, ""
    if matched:
        ev = matched[0].ev
        assert ev is not None
        parts = []
        if ev.bound_violation > _bound_tol(ocp):
            parts.append(
                f"the control bounds by {ev.bound_violation:.3g} (tolerance {_bound_tol(ocp):g})"
            )
        if ev.path_violation > _PATH_TOL:
            parts.append(
                f"the path constraints by {ev.path_violation:.3g} (tolerance {_PATH_TOL:g}; "
                "they hold at the collocation points only: a finer mesh may help)"
            )
        tol = matched[0].terminal_tol
        if ev.terminal_violation > tol:
            parts.append(
                f"the terminal constraints by {ev.terminal_violation:.3g} (tolerance {tol:g}, "
                f"mesh {list(matched[0].result._nlp.mesh)}; the NLP meets them at its "
                "collocated final state: a finer --mesh or a higher --degree may help)"
            )
        message = "the re-simulated control violates " + " and ".join(parts)
        return matched[0], Status.INFEASIBLE, message
    judged = [j for j in differ if j.ev is not None]
    if not judged:
        errors = "; ".join(f"{j.result.sequence}: {j.error}" for j in differ)
        raise EvaluationError(
            f"the judge cannot re-simulate the control of any converged event sequence ({errors})"
        )
    best_j = min(judged, key=lambda j: j.ev.cost)  # type: ignore[union-attr]
    ev = best_j.ev
    assert ev is not None
    message = (
        f"modelled events {best_j.result.sequence} at t = "
        f"{[round(float(t), 9) for t in best_j.result.event_times]} but the re-simulated "
        f"control gives {_resimulated_names(ocp, ev)} at t = "
        f"{[round(float(e.time), 9) for e in ev.events]}; no candidate sequence "
        f"reproduced its events (tried {[t['sequence'] for t in tried]})"
    )
    return best_j, Status.EVENTS_DIFFER, message


def _assemble(
    ocp: HybridOCP,
    best_j: _Judged,
    degree: int,
    mesh: Any,
    sequence: list[str] | None,
    tried: list[dict[str, Any]],
    perturbation: float,
    solve_time: float,
) -> Solution:
    """The Solution of the chosen candidate (its status not yet set)."""
    best, best_ev = best_j.result, best_j.ev
    assert best_ev is not None
    grid = _at(ocp, best).time_grid()
    controls = best.cell_averages(grid)
    info = {
        "sequence": best.sequence,
        "event_times": [float(t) for t in best.event_times],
        "nlp_cost": best.nlp_cost,
        "resimulated_cost_gap": float(abs(best_ev.cost - best.nlp_cost)),
        "lambda0": [float(x) for x in best.lambda0],
        "jump_multipliers": [float(x) for x in best.jump_multipliers],
        "iterations": best.iterations,
        "ipopt_status": best.status,
        "active_path_multiplier": best.active_path,
        "mesh": list(best._nlp.mesh),
        "phase_durations": _phase_durations(best),
        "bound_violation": float(best_ev.bound_violation),
        "path_violation": float(best_ev.path_violation),
        "horizon": float(best.horizon),
        "free_horizon": bool(ocp.free_horizon),
        "terminal_constraints": bool(ocp.has_terminal_constraints),
        "terminal_violation": float(best_ev.terminal_violation),
        "guess_perturbation": perturbation,
        "candidates": tried,
    }
    arrays = {
        "event_times": np.array(best.event_times),
        "lambda0": np.array(best.lambda0),
        "element_bounds": best.element_bounds,
        "radau_controls": np.concatenate(best.controls, axis=1),
        "control_nodes": np.array(best._nlp.rad.tau[1:]),  # u(t) rebuilt without casadi
    }
    if ocp.has_bounds:  # u(t) is clipped into them (also after saving and loading)
        arrays["u_min"] = np.array(ocp.u_min, dtype=float)
        arrays["u_max"] = np.array(ocp.u_max, dtype=float)
    if best.event_controls is not None:  # the resets' own controls, which the judge applies
        arrays["event_controls"] = np.array(best.event_controls)
    sol = Solution(
        method="dt",
        scene=ocp.name,
        controls=controls,
        time_grid=grid,
        cost=float(best_ev.cost),
        terminal_cost=float(best_ev.terminal_cost),
        running_cost=float(best_ev.running_cost),
        events=best_ev.event_dicts(),
        state_times=np.array(best_ev.times),
        states=np.array(best_ev.states),
        costate_times=best.costate_times,
        costates=best.costates,
        settings={
            "degree": int(degree),
            "mesh": mesh if mesh is not None else _DEFAULT_MESH,
            "sequence": list(sequence) if sequence is not None else None,
        },
        timings={"solve_time_s": solve_time},
        info=info,
        arrays=arrays,
    )
    return sol.bind(ocp)


class _PiecewisePolynomial:
    """``u(t)`` of a transcription Solution, rebuilt from its arrays."""

    def __init__(self, solution: Any) -> None:
        try:
            self.eb = np.asarray(solution.arrays["element_bounds"], dtype=float)
            vals = np.asarray(solution.arrays["radau_controls"], dtype=float)
            self.d = int(solution.settings["degree"])
        except (KeyError, AttributeError, TypeError):
            raise HybridocError(
                "not a direct-transcription Solution (no collocation data)"
            ) from None
        self.rad = _Radau.make(self.d)
        self.vals = vals.reshape(vals.shape[0], -1, self.d)  # (nu, elements, d)
        nu = self.vals.shape[0]
        self.lo = np.asarray(solution.arrays.get("u_min", np.full(nu, -np.inf)), dtype=float)
        self.hi = np.asarray(solution.arrays.get("u_max", np.full(nu, np.inf)), dtype=float)

    def at(self, t: np.ndarray) -> np.ndarray:
        return lagrange_pieces(t, self.eb, self.rad.tau[1:], self.vals, self.lo, self.hi)


def _cell_averages(
    u_at: Callable[[np.ndarray], np.ndarray], bounds: np.ndarray, grid: np.ndarray, n_gauss: int = 6
) -> np.ndarray:
    """Cell averages on ``grid`` of a function smooth between ``bounds`` (Gauss-Legendre)."""
    xg, wg = np.polynomial.legendre.leggauss(n_gauss)
    cuts = np.union1d(grid, bounds)
    cuts = cuts[(cuts >= grid[0]) & (cuts <= grid[-1])]
    a, b = cuts[:-1], cuts[1:]
    keep = b - a > 0
    a, b = a[keep], b[keep]
    mid, half = 0.5 * (a + b), 0.5 * (b - a)
    tq = (mid[:, None] + half[:, None] * xg[None, :]).ravel()
    uq = u_at(tq).reshape(a.size, n_gauss, -1)
    integ = np.einsum("q,pqu->pu", wg, uq) * half[:, None]
    cell = np.clip(np.searchsorted(grid, mid, side="right") - 1, 0, grid.size - 2)
    out = np.zeros((grid.size - 1, uq.shape[-1]))
    np.add.at(out, cell, integ)
    return out / np.diff(grid)[:, None]


def _pieces_at_one_time(
    bounds: np.ndarray,
    nodes: np.ndarray,
    values: np.ndarray,
    lo: np.ndarray | float,
    hi: np.ndarray | float,
) -> Callable[[float], np.ndarray]:
    """``t -> lagrange_pieces([t], bounds, nodes, values, lo, hi)[0]``, bit for bit.

    The judge calls a continuous control at every stage of its integrator, one time at a
    time (6000 to 10000 calls per transcription on the hopper), where
    :func:`~hybridoc.solution.lagrange_pieces`'s dozen array operations on one-element
    arrays cost about 40 us a call idle. Here the element and the Lagrange basis are plain
    floats, computed by the same operations in the same order (so the same roundings), and
    the weighted sum and the clip are the very ``einsum`` and ``clip`` of
    ``lagrange_pieces`` on arrays of the same shapes and layouts: the einsum's summation
    order depends on its SIMD kernel (two lanes here, not left to right), which only the
    same call reproduces on every machine.
    """
    b = np.asarray(bounds, dtype=float).tolist()
    last = len(b) - 2
    nd = np.asarray(nodes, dtype=float).tolist()
    d = len(nd)
    den = [[nd[j] - nd[m] for m in range(d)] for j in range(d)]
    V = np.asarray(values, dtype=float)
    # each element's values as lagrange_pieces indexes them (values[:, idx, :], idx an array)
    per = [V[:, np.array([e]), :] for e in range(V.shape[1])]
    others = [[m for m in range(d) if m != j] for j in range(d)]

    def u(t: float) -> np.ndarray:
        t = float(t)
        e = min(max(bisect.bisect_right(b, t) - 1, 0), last)
        a = b[e]
        s = (t - a) / (b[e + 1] - a)
        basis = []
        for j in range(d):
            w = 1.0
            dj = den[j]
            for m in others[j]:
                w *= (s - nd[m]) / dj[m]
            basis.append(w)
        # ndarray.clip: what np.clip calls, without its 3 us of dispatch
        return np.einsum("nj,unj->nu", np.array([basis]), per[e]).clip(lo, hi)[0]

    return u


def control_function(solution: Any) -> Callable[[float], np.ndarray]:
    """The continuous-time control ``u(t)`` of a Solution returned by :func:`solve_dt`.

    Rebuilt from ``solution.arrays`` (``element_bounds``, ``radau_controls``) and the
    collocation degree, so it also works for a saved and reloaded solution.
    """
    pp = _PiecewisePolynomial(solution)
    return _pieces_at_one_time(pp.eb, pp.rad.tau[1:], pp.vals, pp.lo, pp.hi)


def resample_controls(solution: Any, grid: np.ndarray) -> np.ndarray:
    """Cell averages of a transcription Solution's ``u(t)`` on any time grid.

    Parameters
    ----------
    solution
        A Solution from :func:`solve_dt`.
    grid
        Increasing times from 0 to T (e.g. ``scene.with_steps(N).time_grid()``).

    Returns
    -------
    numpy.ndarray
        ``(len(grid) - 1, nu)`` averages (exact up to rounding: Gauss-Legendre on each
        polynomial piece).
    """
    pp = _PiecewisePolynomial(solution)
    return _cell_averages(pp.at, pp.eb, np.asarray(grid, dtype=float))
