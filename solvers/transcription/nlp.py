"""The transcribed NLP of one event sequence: phases, mesh, variables and constraints, in the
problem's own units (the package notes, "Units"), and its size before it is built.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP
from hybridoc.solvers.transcription.collocation import Radau
from hybridoc.solvers.transcription.monitor import IterationCallback
from hybridoc.solvers.transcription.options import MAX_ITER

__all__ = [
    "MAX_NLP_SIZE",
    "PhaseNLP",
    "guard_scales",
    "nlp_for",
    "nlp_size",
    "rounding_level",
    "terminal_count",
]


MAX_NLP_SIZE = 100_000
"""The most variables plus constraints of one transcribed NLP, estimated before it is built
(:func:`nlp_size`). IPOPT's iterations grow faster than the NLP: measured on 2 cores, 13
discs (78 disc pairs, each kept apart at every node), one phase: 11 224 -> 0.13 s per
iteration (500 iterations in 63 s); 44 344 -> 5.6 s to build and more than 290 s in IPOPT.
Problems of the documentation and tests stay under 20 000. Beyond this bound a solve would
run for hours: reduce ``mesh``, the events (``sequence``, another initial guess) or the
bodies."""


_NLPS: weakref.WeakKeyDictionary[HybridOCP, dict[Any, Any]] = weakref.WeakKeyDictionary()


_GUARD_SCALES: weakref.WeakKeyDictionary[HybridOCP, np.ndarray] = weakref.WeakKeyDictionary()


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
        physical rows are ``scale * expr``, what :meth:`PhaseNLP.mult` unscales by)."""
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


class PhaseNLP:
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
        self.rad = Radau.make(degree)
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
        self.gs = guard_scales(ocp)

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
        self.callback: IterationCallback | None = None

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
                self.callback = IterationCallback(self.n_w, self.n_g, self.lbg, self.ubg, self.cs)
            opts = {
                "ipopt.tol": 1e-12,
                "ipopt.acceptable_tol": max(1e-9, 100 * rounding_level(self.ocp)),
                "ipopt.max_iter": MAX_ITER,
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


def rounding_level(ocp: HybridOCP) -> float:
    """The relative rounding of the problem's functions at its states, in scaled units:
    ``eps max(1, max |s0_i| / sigma_i)`` (``s0`` the initial state). A problem far from the
    origin in its own lengths (positions ``3e5`` with lengths ``1e-3``) evaluates its guards
    and costs on positions rounded to ``eps |s|``, noise that no iterate can push below:
    IPOPT's acceptable level is set above it (``1e-9`` otherwise)."""
    x0 = np.abs(np.asarray(ocp.x0, dtype=float))
    return float(np.finfo(float).eps * max(1.0, float(np.max(x0 / ocp.scales.state_array))))


def guard_scales(ocp: HybridOCP) -> np.ndarray:
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


def terminal_count(ocp: HybridOCP) -> int:
    """The number of terminal constraints (equalities and inequalities)."""
    fns = (ocp.terminal_eq, ocp.terminal_ineq)
    return sum(int(fn.size1_out(0)) for fn in fns if fn is not None)


def nlp_size(
    ocp: HybridOCP, guards: Sequence[int], degree: int, mesh: Sequence[int]
) -> tuple[int, int]:
    """``(variables, constraints)`` of the transcribed NLP of one sequence, without building
    it (the same count as :class:`PhaseNLP`: states and controls at the nodes, collocation
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
    n_g = 1 + nx + terminal_count(ocp)
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
            "use a smaller --mesh, fewer events (--sequence, another --controls), fewer bodies, "
            "or --method gd"
        )


def nlp_for(
    ocp: HybridOCP,
    guards: Sequence[int],
    degree: int,
    mesh: Sequence[int],
    fractions: Sequence[np.ndarray | None] | None = None,
) -> PhaseNLP:
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
        cache[key] = PhaseNLP(ocp, guards, degree, mesh, fractions)
    return cache[key]
